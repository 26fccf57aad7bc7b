"""The wire format between the world and the agent processes (schema version 3).

Every packet is one little-endian header followed by a kind-specific body:

    header (28 bytes): magic b"TSWM", schema u8, kind u8, run u32, step u32, envs u16, round u8, pad u8,
                       sender u16, nonce u64
        run     a random id the world draws at start; packets of another run are foreign
                (HELLO: the run the agent is in, 0 before its first observation)
        step    the control step the packet belongs to (the world's counter, from 0)
        envs    B, the number of parallel worlds the packet covers (1 on a real robot)
        round   the communication round (MSG, TABLE)
        sender  the agent id (OBS, REFUSE: the agent it is addressed to); ids are 0..65535
        nonce   the agent instance: a random non-zero u64 each agent process draws at start and
                puts in every packet it sends (HELLO, MSG, ACT). The world binds id -> nonce at
                the first HELLO of the right export and takes that id's actions from that
                nonce only; its OBS and REFUSE carry the nonce of the instance they are for
                (OBS: 0 while the id is unbound, and no agent acts on it). STOP: 0.

    OBS   world -> agent i    M u16, L u16, F u8, K u16, S u16, then per world (B of them):
                              self_obs f32 [B, 4], entities f32 [B, L, F], entity_mask u8 [B, L],
                              heard u16 [B, K], offsets f32 [B, K, 2], fresh u8 [B],
                              sensed u16 [B, S], sensed_offsets f32 [B, S, 2], occupancy f32 [B, S]
                              heard: the agents i hears this step, in the order it stacks their
                              messages (0xFFFF: an empty slot); offsets: each one's position minus
                              i's, what a range sensor reports of the agents it hears (relative
                              edges); fresh: the world's episode starts at this step.
                              A radio policy (landmark_order "radio") gets L = 0 and composes its
                              landmark rows itself from its auction: sensed are the landmarks within
                              its sense radius, nearest first (at most 2 KL), their offsets and
                              occupancy readings (deploy/radio.py); S = 0 otherwise
    TABLE agent -> neighbours S u16, count u16 [B], lid u16 [B, S], epoch u16 [B, S], price f32 [B, S],
                              holder u16 [B, S] (0xFFFF: nobody): the sender's radio auction table
                              after its bid in round ``round`` (radio policies, R rounds before the
                              network's); ENTRY_BYTES per entry on the air
    MSG   agent -> neighbours message f32 [B, 2, H]  (the sender's attention key and value, manifest "message")
    ACT   agent -> world      M u16, actions u8 [B] (below the policy's 5 or 9), attention f32 [B, M], then the
                              agent's stats f32 [len(STATS)]
    HELLO agent -> all        export manifest sha256 (64 ascii hex): an agent of another export is refused;
                              then n u16 and the n agent ids whose hellos it has heard (its routes from
                              them exist: the world starts once every agent hears every other).
                              Sent every 0.25 s before the agent's first observation and every 1 s
                              after it (so a restarted world hears its team at once, and a live
                              agent's binding is never taken by another instance)
    STOP  world -> agents     empty: the run is over
    REFUSE world -> agent i   reason u8 (REFUSED_ID: another instance holds id i; REFUSED_EXPORT: the
                              agent runs another export), the world's manifest sha256 (64 ascii):
                              the instance named by the header's nonce is not in this team

``decode`` raises ``PacketError`` (one line naming what is wrong) on anything else; receivers
drop such a packet, count it and go on.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from deploy.radio import Table

SCHEMA_VERSION = 4  # 2: HELLO carries the agents heard; 3: the agent instance's nonce, REFUSE; 4: OBS
# carries the agents heard as lists with their offsets, landmark features and masks, and sensing; TABLE
MAGIC = b"TSWM"
OBS, MSG, ACT, HELLO, STOP, REFUSE, TABLE = 1, 2, 3, 4, 5, 6, 7
KINDS = {OBS: "obs", MSG: "msg", ACT: "act", HELLO: "hello", STOP: "stop", REFUSE: "refuse", TABLE: "table"}
ACTIONS = 9  # at most: the paper's 5 and the fine action space's 4 more (taichi_swarm.physics)
NONE = 0xFFFF  # an empty slot of a u16 id list (heard, sensed) or nobody (a table's holder)
REFUSED_ID, REFUSED_EXPORT = 1, 2
_HEADER = struct.Struct("<4sBBIIHBBHQ")
HEADER_BYTES = _HEADER.size
_REASON = struct.Struct("<B")
_MEL = struct.Struct("<HH")
_OBS = struct.Struct("<HHBHH")
_N = struct.Struct("<H")
# what an agent reports with every action (cumulative since it started, except latency)
STATS = (
    "decision_s",  # obs received -> action sent, this step
    "cpu_s",  # process CPU time
    "msgs_sent",
    "bytes_sent",
    "msgs_heard",  # per-world messages of neighbours used in a round
    "late",  # arrived after its round's deadline (stale step or round)
    "malformed",
    "foreign",  # another run, another team size or hidden width, a sender out of range
    "version",  # another schema version
    "missed",  # expected neighbour messages not there by the round deadline (per world)
    "overflow",  # dropped by a bound on what is kept: the inbox full, a message too many steps ahead
)


class PacketError(ValueError):
    """A packet that is not one of this schema's: truncated, wrong magic, wrong sizes."""


class VersionError(PacketError):
    """A packet of another schema version."""


@dataclass
class Header:
    kind: int
    run: int
    step: int
    envs: int
    round: int
    sender: int
    nonce: int = 0


def header_bytes(kind: int, run: int, step: int, envs: int, round_: int, sender: int, nonce: int = 0) -> bytes:
    return _HEADER.pack(MAGIC, SCHEMA_VERSION, kind, run, step, envs, round_, 0, sender, nonce)


def read_header(data: bytes) -> Header:
    # the version first: another schema's header has another size (version 2's: 20 bytes)
    if len(data) > 4 and data[:4] == MAGIC and data[4] != SCHEMA_VERSION:
        raise VersionError(f"packet of schema version {data[4]}; this side speaks {SCHEMA_VERSION}")
    if len(data) < HEADER_BYTES:
        raise PacketError(f"packet of {len(data)} bytes is shorter than the {HEADER_BYTES}-byte header")
    magic, version, kind, run, step, envs, round_, _, sender, nonce = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise PacketError(f"packet does not start with {MAGIC!r} (got {magic!r})")
    if kind not in KINDS:
        raise PacketError(f"unknown packet kind {kind}")
    return Header(kind, run, step, envs, round_, sender, nonce)


def _array(data: bytes, offset: int, dtype, shape: tuple[int, ...]) -> tuple[np.ndarray, int]:
    count = math.prod(shape)  # (not np.prod: this runs for every packet an agent reads)
    n = count * np.dtype(dtype).itemsize
    if offset + n > len(data):
        raise PacketError(f"packet body is truncated (needs {offset + n} bytes, has {len(data)})")
    return np.frombuffer(data, dtype, count=count, offset=offset).reshape(shape), offset + n


def _exact(data: bytes, end: int, what: str) -> None:
    if end != len(data):
        raise PacketError(f"{what} packet has {len(data) - end} bytes after its body")


# ----------------------------------------------------------------------------- encoders
@dataclass
class Observation:
    """What the world sends agent i for its B worlds (the OBS body, decoded)."""

    self_obs: np.ndarray  # float32 [B, 4]
    entities: np.ndarray  # float32 [B, L, F]
    entity_mask: np.ndarray  # bool [B, L]
    heard: np.ndarray  # int [B, K]; -1: an empty slot
    offsets: np.ndarray  # float32 [B, K, 2]
    fresh: np.ndarray  # bool [B]
    agents: int = 0  # M
    sensed: np.ndarray | None = None  # int [B, S]; -1: none (radio policies)
    sensed_offsets: np.ndarray | None = None  # float32 [B, S, 2]
    occupancy: np.ndarray | None = None  # float32 [B, S]


def _ids(ids: np.ndarray) -> bytes:
    ids = np.asarray(ids, np.int64)
    return np.where(ids < 0, NONE, ids).astype("<u2").tobytes()


def obs_packet(run: int, step: int, agent: int, o: Observation, nonce: int = 0) -> bytes:
    """``o`` for ``agent``; ``nonce``: the instance of ``agent`` the world has bound (0: none yet)."""
    B, L, F = o.entities.shape
    K = o.heard.shape[1]
    S = 0 if o.sensed is None else o.sensed.shape[1]
    parts = [
        header_bytes(OBS, run, step, B, 0, agent, nonce),
        _OBS.pack(o.agents, L, F, K, S),
        np.ascontiguousarray(o.self_obs, np.float32).tobytes(),
        np.ascontiguousarray(o.entities, np.float32).tobytes(),
        np.ascontiguousarray(o.entity_mask, np.uint8).tobytes(),
        _ids(o.heard),
        np.ascontiguousarray(o.offsets, np.float32).tobytes(),
        np.ascontiguousarray(o.fresh, np.uint8).tobytes(),
    ]
    if S:
        parts += [
            _ids(o.sensed),
            np.ascontiguousarray(o.sensed_offsets, np.float32).tobytes(),
            np.ascontiguousarray(o.occupancy, np.float32).tobytes(),
        ]
    return b"".join(parts)


def table_packet(run: int, step: int, round_: int, sender: int, tables, nonce: int = 0) -> bytes:
    """``tables``: the sender's deploy.radio.Table in each of the B worlds."""
    B = len(tables)
    S = max((t.lid.size for t in tables), default=0)
    lid, epoch, holder = (np.full((B, S), NONE, "<u2") for _ in range(3))
    price = np.zeros((B, S), "<f4")
    count = np.zeros(B, "<u2")
    for b, t in enumerate(tables):
        n = count[b] = t.lid.size
        lid[b, :n], epoch[b, :n], price[b, :n] = t.lid, t.epoch, t.price
        holder[b, :n] = np.where(t.holder < 0, NONE, t.holder)
    head = header_bytes(TABLE, run, step, B, round_, sender, nonce) + _N.pack(S)
    return b"".join((head, count.tobytes(), lid.tobytes(), epoch.tobytes(), price.tobytes(), holder.tobytes()))


def msg_packet(run: int, step: int, round_: int, sender: int, message: np.ndarray, nonce: int = 0) -> bytes:
    """message [B, 2, H]."""
    return (
        header_bytes(MSG, run, step, message.shape[0], round_, sender, nonce)
        + np.ascontiguousarray(message, np.float32).tobytes()
    )


def act_packet(
    run: int, step: int, sender: int, actions: np.ndarray, attention: np.ndarray, stats, nonce: int = 0
) -> bytes:
    """actions [B] ints in 0..ACTIONS - 1, attention [B, M], stats: the values of STATS in order."""
    B, M = attention.shape
    return b"".join(
        (
            header_bytes(ACT, run, step, B, 0, sender, nonce),
            _MEL.pack(M, len(STATS)),
            np.asarray(actions, np.uint8).tobytes(),
            np.ascontiguousarray(attention, np.float32).tobytes(),
            np.asarray(stats, np.float32).tobytes(),
        )
    )


def hello_packet(run: int, sender: int, manifest_sha256: str, heard=(), nonce: int = 0) -> bytes:
    """``run``: the run the agent is in (0: none yet)."""
    heard = np.asarray(sorted(heard), "<u2")
    return b"".join(
        (
            header_bytes(HELLO, run, 0, 0, 0, sender, nonce),
            manifest_sha256.encode("ascii"),
            _N.pack(len(heard)),
            heard.tobytes(),
        )
    )


def stop_packet(run: int) -> bytes:
    return header_bytes(STOP, run, 0, 0, 0, 0)


def refuse_packet(run: int, agent: int, nonce: int, reason: int, manifest_sha256: str) -> bytes:
    """The world to the instance ``nonce`` of agent ``agent``: it is not in this team (``reason``)."""
    return header_bytes(REFUSE, run, 0, 0, 0, agent, nonce) + _REASON.pack(reason) + manifest_sha256.encode("ascii")


# ----------------------------------------------------------------------------- decoders
def decode_obs(data: bytes) -> tuple[Header, Observation]:
    h = read_header(data)
    if h.kind != OBS:
        raise PacketError(f"expected an obs packet, got {KINDS[h.kind]}")
    if len(data) < HEADER_BYTES + _OBS.size:
        raise PacketError("obs packet is truncated")
    M, L, F, K, S = _OBS.unpack_from(data, HEADER_BYTES)
    B = h.envs
    if B < 1 or M < 1 or h.sender >= M or F not in (2, 3):
        raise PacketError(f"obs packet for agent {h.sender} of {M} agents in {B} worlds, {F} landmark features")
    off = HEADER_BYTES + _OBS.size
    self_obs, off = _array(data, off, np.float32, (B, 4))
    entities, off = _array(data, off, np.float32, (B, L, F))
    mask, off = _array(data, off, np.uint8, (B, L))
    heard, off = _array(data, off, np.dtype("<u2"), (B, K))
    offsets, off = _array(data, off, np.float32, (B, K, 2))
    fresh, off = _array(data, off, np.uint8, (B,))
    o = Observation(self_obs, entities, mask.astype(bool), _id_list(heard, M, "heard"), offsets, fresh.astype(bool), M)
    finite = [self_obs, entities, offsets]
    if S:
        sensed, off = _array(data, off, np.dtype("<u2"), (B, S))
        o.sensed = _id_list(sensed, None, "sensed")
        o.sensed_offsets, off = _array(data, off, np.float32, (B, S, 2))
        o.occupancy, off = _array(data, off, np.float32, (B, S))
        finite += [o.sensed_offsets, o.occupancy]
    _exact(data, off, "obs")
    if not all(np.isfinite(a).all() for a in finite):
        raise PacketError("obs packet holds a non-finite number")
    return h, o


def _id_list(ids: np.ndarray, bound: int | None, what: str) -> np.ndarray:
    out = ids.astype(np.int64)
    out[ids == NONE] = -1
    if bound is not None and (out >= bound).any():
        raise PacketError(f"obs packet's {what} list names agent {int(out.max())} of {bound}")
    return out


def decode_table(data: bytes):
    """-> (header, the sender's deploy.radio.Table in each world)."""
    h = read_header(data)
    if h.kind != TABLE or len(data) < HEADER_BYTES + _N.size or h.envs < 1:
        raise PacketError("table packet must carry its slots and at least one world")
    (S,) = _N.unpack_from(data, HEADER_BYTES)
    B = h.envs
    count, off = _array(data, HEADER_BYTES + _N.size, np.dtype("<u2"), (B,))
    lid, off = _array(data, off, np.dtype("<u2"), (B, S))
    epoch, off = _array(data, off, np.dtype("<u2"), (B, S))
    price, off = _array(data, off, np.dtype("<f4"), (B, S))
    holder, off = _array(data, off, np.dtype("<u2"), (B, S))
    _exact(data, off, "table")
    if (count > S).any() or not np.isfinite(price).all():
        raise PacketError("table packet counts more entries than its slots, or holds a non-finite price")
    tables = []
    for b in range(B):
        n = int(count[b])
        ids = lid[b, :n].astype(np.int32)
        if (np.diff(ids) <= 0).any():
            raise PacketError("table packet's landmark ids are not sorted")
        who = holder[b, :n].astype(np.int32)
        who[who == NONE] = -1
        tables.append(Table(ids, epoch[b, :n].astype(np.int32), price[b, :n].astype(np.float32), who))
    return h, tables


def decode_msg(data: bytes, hidden: int):
    """-> (header, message [B, 2, H]); a message of another hidden width is malformed."""
    h = read_header(data)
    if h.kind != MSG:
        raise PacketError(f"expected a msg packet, got {KINDS[h.kind]}")
    if h.envs < 1:
        raise PacketError("msg packet for 0 worlds")
    message, off = _array(data, HEADER_BYTES, np.float32, (h.envs, 2, hidden))
    _exact(data, off, f"msg (hidden {hidden})")
    if not np.isfinite(message).all():
        raise PacketError("msg packet holds a non-finite number")
    return h, message


def decode_act(data: bytes):
    """-> (header, actions int64 [B], attention [B, M], stats dict)."""
    h = read_header(data)
    if h.kind != ACT:
        raise PacketError(f"expected an act packet, got {KINDS[h.kind]}")
    if len(data) < HEADER_BYTES + _MEL.size:
        raise PacketError("act packet is truncated")
    M, n_stats = _MEL.unpack_from(data, HEADER_BYTES)
    if n_stats != len(STATS):
        raise PacketError(f"act packet carries {n_stats} stats, schema {SCHEMA_VERSION} has {len(STATS)}")
    off = HEADER_BYTES + _MEL.size
    actions, off = _array(data, off, np.uint8, (h.envs,))
    attention, off = _array(data, off, np.float32, (h.envs, M))
    stats, off = _array(data, off, np.float32, (n_stats,))
    _exact(data, off, "act")
    if (actions >= ACTIONS).any():
        raise PacketError(f"act packet holds action {int(actions.max())} (actions are 0..{ACTIONS - 1})")
    return h, actions.astype(np.int64), attention, dict(zip(STATS, stats.tolist(), strict=True))


def decode_hello(data: bytes):
    """-> (header, manifest sha256, the agent ids it has heard: frozenset)."""
    h = read_header(data)
    if h.kind != HELLO or len(data) < HEADER_BYTES + 64 + _N.size:
        raise PacketError("hello packet must carry a 64-character manifest sha256 and the agents heard")
    try:
        sha = data[HEADER_BYTES : HEADER_BYTES + 64].decode("ascii")
    except UnicodeDecodeError:
        raise PacketError("hello packet's manifest sha256 is not ascii") from None
    (n,) = _N.unpack_from(data, HEADER_BYTES + 64)
    heard, off = _array(data, HEADER_BYTES + 64 + _N.size, np.dtype("<u2"), (n,))
    _exact(data, off, "hello")
    return h, sha, frozenset(heard.tolist())


def decode_refuse(data: bytes):
    """-> (header, reason, the world's manifest sha256)."""
    h = read_header(data)
    if h.kind != REFUSE or len(data) != HEADER_BYTES + _REASON.size + 64:
        raise PacketError("refuse packet must carry a reason and a 64-character manifest sha256")
    (reason,) = _REASON.unpack_from(data, HEADER_BYTES)
    if reason not in (REFUSED_ID, REFUSED_EXPORT):
        raise PacketError(f"refuse packet of unknown reason {reason}")
    try:
        sha = data[HEADER_BYTES + _REASON.size :].decode("ascii")
    except UnicodeDecodeError:
        raise PacketError("refuse packet's manifest sha256 is not ascii") from None
    return h, reason, sha

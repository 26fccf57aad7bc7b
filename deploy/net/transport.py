"""Zenoh sessions for the world and the agents, and the key expressions they use.

The world's session is a Zenoh router listening on ``--listen`` (default tcp/127.0.0.1:7447);
each agent is a peer that connects to it and listens on a port of its own, so the agents
find each other through the router (gossip) and exchange their messages peer to peer.
Multicast scouting and shared memory are off: nothing is sent anywhere but the endpoints named. Every
publisher blocks rather than drops under congestion (a loss is a fault we inject, never
one the transport makes up) and is "express" (sent at once, not batched).

Keys, under a namespace ``ns`` (default "swarm"): ``ns/obs/I`` (world -> agent I),
``ns/msg/I`` (agent I -> whoever listens), ``ns/act/I`` (agent I -> world),
``ns/hello/I`` (agent I announces itself), ``ns/refuse/I`` (world -> an instance of agent I it
does not take), ``ns/stop`` (world -> all).
"""

from __future__ import annotations

import json
import queue
import re
import threading
import time

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
_ENDPOINT = re.compile(r"^(tcp|udp|quic|tls)/[^\s/]+:\d{1,5}$")
_NAMESPACE = re.compile(r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$")
# what the inbox holds unread at most: past either bound a packet is dropped on arrival and
# counted (``Endpoint.overflow``), so a flood costs packets, never unbounded memory
INBOX_PACKETS = 65536
INBOX_BYTES = 64 << 20


class TransportError(ValueError):
    """Zenoh is missing, or an endpoint or namespace is not usable."""


def check_endpoint(endpoint: str, what: str) -> str:
    if not _ENDPOINT.match(endpoint):
        raise TransportError(f"{what} {endpoint!r} is not a Zenoh endpoint like tcp/127.0.0.1:7447")
    return endpoint


def check_namespace(ns: str) -> str:
    if not _NAMESPACE.match(ns):
        raise TransportError(f"--ns {ns!r} must be words of letters, digits, '_' or '-' separated by '/'")
    return ns


def _zenoh():
    try:
        import zenoh
    except ImportError:
        raise TransportError(
            "the networked commands need Zenoh: pip install 'eclipse-zenoh>=1.0,<2' (or the 'net' extra)"
        ) from None
    return zenoh


def open_session(mode: str, listen: list[str], connect: list[str]):
    """A Zenoh session in ``mode`` ("router" or "peer") on exactly these endpoints."""
    zenoh = _zenoh()
    for e in listen:
        check_endpoint(e, "--listen")
    for e in connect:
        check_endpoint(e, "--connect")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    conf.insert_json5("scouting/multicast/enabled", "false")
    # no shared-memory pools: the packets are small, and with them each of 50 agent processes on
    # one machine mapped about 900 MB of its peers' segments (measured)
    conf.insert_json5("transport/shared_memory/enabled", "false")
    try:
        return zenoh.open(conf)
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError: port in use, bad address
        raise TransportError(f"cannot open a Zenoh {mode} session on {listen or connect}: {exc}") from None


class Endpoint:
    """A session, its publishers by key, and one inbox queue of (key, bytes, arrival time) for all
    subscriptions, bounded (INBOX_PACKETS, INBOX_BYTES; what does not fit is counted in ``overflow``)."""

    def __init__(self, session, ns: str):
        self.session = session
        self.ns = check_namespace(ns)
        self.inbox: queue.Queue = queue.Queue()
        self._pubs: dict[str, object] = {}
        self._subs: list = []
        self._lock = threading.Lock()  # (Zenoh's callback thread adds, the reader takes)
        self._queued_bytes = 0
        self.overflow = 0
        self.sent = 0
        self.sent_bytes = 0

    def key(self, *parts) -> str:
        return "/".join([self.ns, *map(str, parts)])

    def _arrive(self, key: str, data: bytes) -> None:
        t = time.perf_counter()
        with self._lock:
            if self.inbox.qsize() >= INBOX_PACKETS or self._queued_bytes + len(data) > INBOX_BYTES:
                self.overflow += 1  # dropped, never blocking Zenoh's thread
                return
            self._queued_bytes += len(data)
        self.inbox.put((key, data, t))

    def subscribe(self, *parts) -> None:
        def on_sample(sample, ep=self):
            ep._arrive(str(sample.key_expr), sample.payload.to_bytes())

        self._subs.append(self.session.declare_subscriber(self.key(*parts), on_sample))

    def _publisher(self, key: str):
        pub = self._pubs.get(key)
        if pub is None:
            zenoh = _zenoh()
            pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK, express=True)
            self._pubs[key] = pub
        return pub

    def matched(self, *parts) -> bool:
        """Whether a subscriber of this key is known to this session's routes (Zenoh's matching
        status): a packet put before one is, is dropped for want of a route, not lost on the way."""
        return bool(self._publisher(self.key(*parts)).matching_status.matching)

    def publish(self, data: bytes, *parts) -> None:
        self._publisher(self.key(*parts)).put(data)
        self.sent += 1
        self.sent_bytes += len(data)

    def get(self, timeout: float):
        """The next (key, data, t_arrival), or None after ``timeout`` seconds."""
        try:
            item = self.inbox.get(timeout=max(timeout, 0.0))
        except queue.Empty:
            return None
        with self._lock:
            self._queued_bytes -= len(item[1])
        return item

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        for p in self._pubs.values():
            p.undeclare()
        self.session.close()

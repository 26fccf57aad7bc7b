"""``swarm export | execute | replay``: argument parsing only; the work is imported lazily
(``swarm execute`` and ``swarm replay`` never import torch)."""

from __future__ import annotations

import argparse
import os
import sys


def _fail(cmd: str, exc: BaseException | str) -> int:
    print(f"swarm {cmd}: error: {exc}", file=sys.stderr)
    return 2


def _parser(prog: str, description: str) -> argparse.ArgumentParser:
    return argparse.ArgumentParser(prog=prog, description=description)


def _parse(parser: argparse.ArgumentParser, argv: list[str]):
    """argparse, but returning 2 instead of raising SystemExit from a library call."""
    try:
        return parser.parse_args(argv), None
    except SystemExit as exc:
        return None, int(exc.code or 0)


# ----------------------------------------------------------------------------- export
def export_main(argv: list[str]) -> int:
    ap = _parser(
        "swarm export", "Export a checkpoint to per-agent ONNX pieces (encode, round, heads) and a manifest.json."
    )
    ap.add_argument("checkpoint", help="checkpoint file or run directory")
    ap.add_argument("--out", required=True, help="output directory (created)")
    ap.add_argument("--task", default=None, help="task to record in the manifest (default: the training task)")
    ap.add_argument("--agents", type=int, default=None, help="team size to record (default: the training size)")
    ap.add_argument("--comm", choices=("uc", "rc"), default=None, help="communication to record (default: training)")
    ap.add_argument("--comm-radius", type=float, default=None, help="rc radius to record (default: training)")
    args, code = _parse(ap, argv)
    if args is None:
        return code
    if not os.path.exists(args.checkpoint):
        return _fail("export", f"checkpoint {args.checkpoint} does not exist")
    if args.agents is not None and args.agents < 1:
        return _fail("export", f"--agents must be >= 1, got {args.agents}")
    import logging

    for name in ("torch.onnx", "torch.onnx._internal.exporter._registration"):
        logging.getLogger(name).setLevel(logging.ERROR)  # "torchvision is not installed" noise
    from deploy.export import export
    from trainer.checkpoint import CheckpointError

    try:
        manifest = export(
            args.checkpoint,
            args.out,
            {"task": args.task, "agents": args.agents, "comm": args.comm, "comm_radius": args.comm_radius},
        )
    except (CheckpointError, ValueError, FileExistsError, OSError) as exc:
        return _fail("export", exc)
    files = ", ".join(f["file"] for f in manifest["files"].values())
    print(
        f"exported {args.checkpoint} -> {args.out}: {files}, manifest.json "
        f"(K={manifest['rounds']}, H={manifest['hidden']}, entity_mode={manifest['entity_mode']}, "
        f"task={manifest['task']['task']})"
    )
    return 0


# ----------------------------------------------------------------------------- execute
def execute_main(argv: list[str]) -> int:
    from deploy.video import add_output_options, open_recorders

    ap = _parser(
        "swarm execute",
        "Run exported models decentralised: one onnxruntime agent per agent, messages "
        "only along the communication graph; prints S%, T, DIST per drop rate.",
    )
    ap.add_argument("directory", help="directory written by `swarm export`")
    ap.add_argument("--task", default=None, help="coverage | formation | line (default: the manifest's)")
    ap.add_argument("--agents", type=int, default=None, help="team size M (default: the manifest's)")
    ap.add_argument("--episodes", type=int, default=10, help="episodes, one per environment (default 10)")
    ap.add_argument("--comm", choices=("uc", "rc"), default=None, help="communication graph (default: manifest)")
    ap.add_argument("--comm-radius", type=float, default=None, help="rc radius (default: the manifest's)")
    ap.add_argument(
        "--drop",
        type=float,
        nargs="+",
        default=[0.0],
        metavar="P",
        help="message drop probabilities, one row each (e.g. --drop 0 0.1 0.3)",
    )
    ap.add_argument("--delay", type=int, default=0, metavar="K", help="deliver messages K steps late (default 0)")
    ap.add_argument("--record", default=None, metavar="FILE.rrd", help="write a Rerun recording (first drop rate)")
    add_output_options(ap, "render the first drop rate's episodes to a .gif / .mp4 (or PNG frames directory)")
    ap.add_argument("--seed", type=int, default=12345, help="seed of the episodes and of the drops")
    ap.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads per session (default 1)")
    ap.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args, code = _parse(ap, argv)
    if args is None:
        return code
    from deploy.executor import DeployError, ExportedModel, format_table, resolve_settings, run_episodes

    try:
        if args.threads < 1:
            raise DeployError(f"--threads must be >= 1, got {args.threads}")
        from taichi_swarm.files import ensure_writable

        for out, what in ((args.json, "--json"), (args.record, "--record")):
            if out:
                ensure_writable(out, what)
        if args.video:
            from deploy.video import check_video_path

            check_video_path(args.video)  # before any episode runs
        model = ExportedModel(args.directory)
        settings = [  # every setting checked (ExecuteSettings) before any episode runs
            resolve_settings(
                model, args.task, args.agents, args.comm, args.comm_radius,
                episodes=args.episodes, drop=p, delay=args.delay, seed=args.seed,
            )
            for p in args.drop
        ]  # fmt: skip
        rows = []
        for k, s in enumerate(settings):
            recorder = open_recorders(args, s.task, s.episodes, s.agents, s.comm, s.comm_radius) if k == 0 else None
            try:
                rows.append(run_episodes(model, s, recorder=recorder, threads=args.threads))
            finally:
                if recorder is not None:
                    recorder.close()
            if recorder is not None:
                recorder.report()
    except (DeployError, ValueError, OSError) as exc:
        return _fail("execute", exc)
    print(format_table(rows))
    if args.json:
        from taichi_swarm.files import atomic_write_json

        atomic_write_json(args.json, {"directory": args.directory, "rows": rows})
    return 0


# ----------------------------------------------------------------------------- replay
def replay_main(argv: list[str]) -> int:
    from deploy.video import add_output_options

    ap = _parser("swarm replay", "Inspect a Rerun recording (--stats) or open it in a viewer.")
    ap.add_argument("file", help="a .rrd file written by --record")
    ap.add_argument("--stats", action="store_true", help="print a summary (entity paths, rows, steps) and exit")
    ap.add_argument("--serve-web", action="store_true", help="serve the web viewer on 127.0.0.1 (no GPU needed)")
    ap.add_argument("--port", type=int, default=None, help="web viewer port (with --serve-web)")
    add_output_options(ap, "render the recording to a .gif / .mp4 (or a PNG frames directory)", record_envs=False)
    args, code = _parse(ap, argv)
    if args is None:
        return code
    if os.path.isdir(args.file):
        return _fail("replay", f"{args.file} is a directory: pass the .rrd file written by --record")
    if not os.path.isfile(args.file):
        return _fail("replay", f"recording {args.file} does not exist")
    from deploy import replay

    if not replay.looks_like_rrd(args.file):
        return _fail(
            "replay", f"{args.file} is not a Rerun recording (.rrd files start with 'RRF'; written by --record)"
        )

    if args.video:
        from deploy.video import check_video_path, frames_from_recording, render

        try:
            check_video_path(args.video)
            frames, task, M, outcomes = frames_from_recording(args.file)
            render(frames, args.video, task, M, outcomes)
        except (ValueError, OSError) as exc:
            return _fail("replay", exc)
        print(f"video: {args.video} ({frames[0]['pos'].shape[0]} environments, {len(frames) - 1} steps)")
        return 0
    if args.stats:
        try:
            summary = replay.summarize(args.file)
        except Exception as exc:  # noqa: BLE001 - reader errors vary: report, no traceback
            return _fail("replay", f"cannot read {args.file} as a Rerun recording ({exc})")
        print(replay.format_summary(summary))
        return 0
    if not args.serve_web and not replay.has_display():
        return _fail(
            "replay",
            "no display found (DISPLAY/WAYLAND_DISPLAY unset): the native Rerun viewer needs a "
            "display and a GPU. Use `swarm replay FILE --serve-web` and open the printed URL, "
            "or `swarm replay FILE --stats` for a text summary",
        )
    return replay.view(args.file, serve_web=args.serve_web, port=args.port)

"""``swarm export | execute | replay``: argument parsing only; the work is imported lazily
(``swarm execute`` and ``swarm replay`` never import torch)."""

from __future__ import annotations

import os
import tempfile

from swarm_cli.options import ExecuteOptions, ExportOptions, ReplayOptions, fail, parse


# ----------------------------------------------------------------------------- export
def export_main(argv: list[str]) -> int:
    args = parse(ExportOptions, argv, "swarm export")
    from trainer.zoo import looks_like_name

    if not os.path.exists(args.checkpoint) and not looks_like_name(args.checkpoint):  # a zoo name loads below
        return fail("swarm export", f"checkpoint {args.checkpoint} does not exist")
    _quiet_exporter()
    from deploy.export import export
    from trainer.checkpoint import CheckpointError

    try:
        manifest = export(
            args.checkpoint,
            args.out,
            {"task": args.task, "agents": args.agents, "comm": args.comm, "comm_radius": args.comm_radius},
            trust_unsigned=args.trust_unsigned,
        )
    except (CheckpointError, ValueError, FileExistsError, OSError) as exc:
        return fail("swarm export", exc)
    files = ", ".join(f["file"] for f in manifest["files"].values())
    print(
        f"exported {args.checkpoint} -> {args.out}: {files}, manifest.json "
        f"(K={manifest['rounds']}, H={manifest['hidden']}, entity_mode={manifest['entity_mode']}, "
        f"task={manifest['task']['task']})"
    )
    return 0


def _quiet_exporter() -> None:
    import logging

    for name in ("torch.onnx", "torch.onnx._internal.exporter._registration"):
        logging.getLogger(name).setLevel(logging.ERROR)  # "torchvision is not installed" noise


# ----------------------------------------------------------------------------- execute
def _export_dir(source: str, tmp: str) -> str:
    """``source`` if it is an export directory; a zoo name or a checkpoint (file or run
    directory) is exported into ``tmp`` first, which needs torch (an export directory does not)."""
    from trainer.zoo import looks_like_name

    run_dir = any(os.path.isfile(os.path.join(source, f)) for f in ("policy.pt", "checkpoint.pt"))
    if not (os.path.isfile(source) or run_dir or (looks_like_name(source) and not os.path.exists(source))):
        return source  # an export directory, or ExportedModel names what is missing
    _quiet_exporter()
    from deploy.executor import DeployError
    from deploy.export import export
    from trainer.checkpoint import CheckpointError

    try:
        export(source, tmp)
    except CheckpointError as exc:
        raise DeployError(str(exc)) from None
    return tmp


def execute_main(argv: list[str]) -> int:
    from deploy.video import open_recorders

    args = parse(ExecuteOptions, argv, "swarm execute")
    from deploy.executor import DeployError, ExportedModel, format_table, resolve_settings, run_episodes

    tmp = tempfile.TemporaryDirectory(prefix="swarm-execute-")
    try:
        args.check_outputs()
        model = ExportedModel(_export_dir(args.directory, tmp.name))
        settings = [  # every setting checked (ExecuteSettings) before any episode runs
            resolve_settings(
                model, args.task, args.agents, args.comm, args.comm_radius,
                episodes=args.episodes, drop=p, delay=args.delay, seed=args.seed, swarm=args.swarm_kwargs(),
                burst_loss=args.burst_loss, burst_len=args.burst_len, hold=args.hold,
            )
            for p in args.drop
        ]  # fmt: skip
        rows = []
        for k, s in enumerate(settings):
            recorder = open_recorders(args, s.task, s.episodes, s.agents, s.comm, s.comm_radius) if k == 0 else None
            try:
                rows.append(run_episodes(model, s, recorder=recorder, threads=args.threads))
            except BaseException:  # (Ctrl-C too): no recording or video written, none replaced
                if recorder is not None:
                    recorder.close(ok=False)
                raise
            if recorder is not None:
                recorder.close()
                recorder.report()
    except (DeployError, ValueError, OSError) as exc:
        return fail("swarm execute", exc)
    finally:
        tmp.cleanup()
    print(format_table(rows))
    if args.json is not None:  # ('' was refused by check_outputs)
        from taichi_swarm.files import atomic_write_json

        atomic_write_json(args.json, {"directory": args.directory, "rows": rows})
    return 0


# ----------------------------------------------------------------------------- replay
def replay_main(argv: list[str]) -> int:
    args = parse(ReplayOptions, argv, "swarm replay")
    if os.path.isdir(args.file):
        return fail("swarm replay", f"{args.file} is a directory: pass the file written by --record")
    from taichi_swarm.files import InputFileError, check_input

    try:  # a FIFO would block the reads below, a device never end
        check_input(args.file, "recording", None)
    except InputFileError as exc:
        return fail("swarm replay", exc)
    from deploy import replay

    if replay.looks_like_npz(args.file):
        return _replay_trajectory(args)
    if not replay.looks_like_rrd(args.file):
        return fail(
            "swarm replay",
            f"{args.file} is neither a trajectory record (.npz) nor a Rerun recording (.rrd, starts with 'RRF'); "
            "both are written by --record",
        )
    if args.video or args.rrd:
        # a Rerun file holds drawing primitives, not the state: nothing is parsed back from it
        return fail(
            "swarm replay",
            f"{args.file} is a Rerun recording: --video and --rrd render a trajectory record; "
            "record one with --record FILE.npz",
        )
    if args.stats:
        try:
            summary = replay.summarize(args.file)
        except Exception as exc:  # noqa: BLE001 - reader errors vary: report, no traceback
            return fail("swarm replay", f"cannot read {args.file} as a Rerun recording ({exc})")
        print(replay.format_summary(summary))
        return 0
    return _view(args, args.file)


def _replay_trajectory(args) -> int:
    """A trajectory record: --stats, --video, --rrd, or the viewer on a temporary .rrd of it."""
    import tempfile

    from deploy import replay
    from deploy.trajectory import Trajectory

    try:
        if args.video is not None:  # ('' too: refused, not skipped)
            from deploy.video import check_video_path

            check_video_path(args.video)  # before the record is read
        if args.rrd is not None:  # ('' too: refused, not skipped)
            from taichi_swarm.files import ensure_writable

            ensure_writable(args.rrd, "--rrd")
        traj = Trajectory.load(args.file)
        if args.stats:
            print(replay.format_trajectory(args.file, traj))
        if args.video:
            from deploy.video import render_trajectory

            render_trajectory(traj, args.video)
            print(f"video: {args.video} ({traj.drawn} environments, {traj.num_steps} steps)")
        if args.rrd:
            from deploy.recording import write_rrd

            write_rrd(traj, args.rrd)
            print(f"recording: {args.rrd}")
        if args.stats or args.video or args.rrd:
            return 0
        missing = _no_display(args)
        if missing:
            return missing
        with tempfile.TemporaryDirectory(prefix="swarm-replay-") as tmp:
            from deploy.recording import write_rrd

            rrd = os.path.join(tmp, os.path.splitext(os.path.basename(args.file))[0] + ".rrd")
            write_rrd(traj, rrd)
            return _view(args, rrd)
    except (ValueError, OSError) as exc:
        return fail("swarm replay", exc)


def _no_display(args) -> int:
    from deploy import replay

    if not args.serve_web and not replay.has_display():
        return fail(
            "swarm replay",
            "no display found (DISPLAY/WAYLAND_DISPLAY unset): the native Rerun viewer needs a "
            "display and a GPU. Use `swarm replay FILE --serve-web` and open the printed URL, "
            "or `swarm replay FILE --stats` for a text summary",
        )
    return 0


def _view(args, path: str) -> int:
    from deploy import replay

    return _no_display(args) or replay.view(path, serve_web=args.serve_web, port=args.port)

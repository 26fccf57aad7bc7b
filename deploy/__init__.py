"""deploy: decentralised execution of trained swarm policies.

    swarm export CKPT --out DIR      per-agent ONNX pieces + manifest.json   (deploy/export.py, uses torch)
    swarm execute DIR --task ...     agent by agent through one onnxruntime session per piece
                                     (deploy/policy.py), a message bus along the communication graph,
                                     drops, bursty loss (deploy/loss.py) and delays (deploy/executor.py, no torch)
    --record FILE.npz / --video      a rollout recorded once as per-step state (deploy/trajectory.py);
                                     Rerun .rrd and GIF/MP4 drawn from it     (deploy/recording.py, deploy/video.py)
    swarm replay FILE.npz            reads that record: --stats, --video, --rrd, the viewer  (deploy/replay.py)
    swarm agent DIR --id I           one agent as its own process, and the simulator as the world of
    swarm world --export DIR         such processes, over Zenoh (deploy/net/, docs/DEPLOY.md); a radio
                                     policy's agent runs its side of the auction (deploy/radio.py)

(the commands live in swarm_cli/deploy.py; its latency benchmark in benchmarks/deploy.py)

Nothing in this package imports torch at import time; only deploy.export does, and
the commands import it lazily.
"""

"""deploy: decentralised execution of trained swarm policies.

    swarm export CKPT --out DIR      per-agent ONNX pieces + manifest.json   (deploy/export.py, uses torch)
    swarm execute DIR --task ...     one onnxruntime agent object per agent, a message bus along the
                                     communication graph, drops and delays  (deploy/executor.py, no torch)
    swarm replay FILE.rrd            Rerun recordings of rollouts            (deploy/recording.py, deploy/replay.py)
    swarm bench deploy               per-agent decision latency, ONNX vs torch (deploy/bench.py)

Nothing in this package imports torch at import time; only deploy.export and
deploy.bench do, and deploy.cli imports them lazily.
"""

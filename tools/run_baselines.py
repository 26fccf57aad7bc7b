"""Train a BenchMARL baseline on a taichi_swarm task, then evaluate it like the paper (S%, T, DIST).

Needs the ``baselines`` extra (``pip install -c <(echo torch==2.13.0) -e ".[baselines]"``).

    python tools/run_baselines.py --algorithm mappo --task coverage --agents 3 \\
        --frames 2000000 --seed 0 --out runs/baselines/mappo-cov3
    python tools/run_baselines.py --algorithm maddpg --task line --agents 3 --frames 1000000 \\
        --out runs/baselines/maddpg-line3 --experiment off_policy_n_optimizer_steps=100

What it does (baselines/run.py):
1. builds the task (baselines/benchmarl_tasks.py) with ``--obs-mode full`` by default: the
   paper's baselines saw every agent's position and velocity, without communication;
   ``--obs-mode local`` gives the paper's own observation instead;
2. runs a BenchMARL Experiment (its default yaml configs for the algorithm, the model and the
   experiment) for ``--frames`` env steps, ``--num-envs`` environments stepped together,
   ``--frames-per-batch`` env steps per iteration; CSV logs and BenchMARL's checkpoints (every
   ``--checkpoint-every`` iterations and at the end, the last two kept, with the optimisers'
   state) go under ``--out``; ``--experiment KEY=VALUE`` overrides any other ExperimentConfig
   field. The same command given again resumes from the latest checkpoint in ``--out`` through
   BenchMARL's ``Experiment.reload_from_file`` (a larger ``--frames`` extends the run); a
   checkpoint of another algorithm, task, seed or batch there is refused, and so is one that
   a stop cut short while it was written (BenchMARL writes in place: remove it to resume from
   the one before);
3. evaluates the trained policy with greedy (deterministic) actions on ``--eval-episodes``
   (500) fresh episodes from ``--eval-seed`` (12345), one episode per environment, and writes
   ``<out>/results.json``: S% (success rate in percent), T (mean episode length, the time limit
   for failures), DIST (coverage: mean landmark-to-closest-agent distance at the end), the
   per-episode values, the configuration and the library versions.

Actions: ``--actions any`` (default) lets BenchMARL choose (continuous when the algorithm
supports it); ``--actions discrete`` / ``continuous`` forces one (MADDPG, IDDPG, MASAC and ISAC
are continuous only; IQL, VDN and QMIX discrete only).
"""

import sys

from baselines.run import main

if __name__ == "__main__":
    sys.exit(main())

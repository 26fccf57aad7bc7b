"""Simulator benchmark: ``python tools/bench_sim.py [options]`` is ``swarm bench sim [options]``."""

import sys

from swarm_cli.bench import main

if __name__ == "__main__":
    sys.exit(main(["sim", *sys.argv[1:]]))

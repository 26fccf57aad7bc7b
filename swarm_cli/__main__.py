"""``python -m swarm_cli ...`` is ``swarm ...``."""

import sys

from swarm_cli.main import main

sys.exit(main())

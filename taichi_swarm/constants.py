"""The simulator's constants that code without Taichi reads: the export manifest's schema and
the agent processes (deploy/), which stay small by never importing Taichi."""

# MPE's physics (physics.py, docs/PAPER.md s.1)
DT = 0.1
DAMPING = 0.25
MASS = 1.0
SENSITIVITY = 5.0  # MPE's agent.accel default (discrete and continuous actions alike)
NUM_ACTIONS = 5  # the paper's discrete actions
NUM_FINE_ACTIONS = 9  # action_space "fine": the paper's five and four quarter pushes (physics.FINE)
COMMS = ("uc", "rc")
ACTION_SPACES = ("discrete", "continuous", "fine")  # physics.py
DEFAULT_ROUNDS = 4  # the radio auction's message rounds per control step, unset (radio.py)
MAX_ROUNDS = 64
# how the network takes the landmark inputs (trainer.model.ModelConfig.entity_mode; deploy/ and
# reproduce/ read it here, without torch): EMP, concatenated (fixed L), or 10 zero-padded slots
ENTITY_MODES = ("emp", "concat", "padded")
EDGE_POSITIONS = ("none", "relative")  # ModelConfig.edge_position, likewise

"""deploy.net: the team as processes, over Zenoh (optional extra ``net``).

    swarm agent DIR --id I      one agent, as on a robot: its ONNX pieces, its observation,
                                its K rounds of messages with whoever it hears (a radio
                                policy first its R auction rounds, ../radio.py)   (agent.py)
    swarm world --export DIR    the Taichi simulator at a fixed control rate; publishes the
                                observations, collects the actions, steps         (world.py)
                                (--spawn-agents: starts the M agents here too)

protocol.py is the wire format (schema version 4: every agent packet carries its process's
nonce, which the world binds to its id; an observation the agents heard and their offsets),
transport.py the Zenoh sessions (loopback by default, no multicast scouting; a bounded inbox),
faults.py the faults injected at the receiving radio, limits.py the bounds every size and time
option is checked against before anything starts.
docs/DEPLOY.md is the integrator's guide. Nothing here imports torch.
"""

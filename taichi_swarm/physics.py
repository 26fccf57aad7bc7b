"""MPE world physics (Lowe et al. 2017, multiagent/core.py), per agent.

See docs/PAPER.md section 1. One step: action force (discrete, the paper's; "fine", the
paper's five and four quarter-strength pushes; or continuous, MPE's continuous mode:
5 clip(u, -1, 1) per axis),
pairwise contact forces between agents, then semi-implicit Euler
    v <- v (1 - damping);  v <- v + F/m dt;  p <- p + v dt.
"""

import taichi as ti

from .constants import ACTION_SPACES, DAMPING, DT, MASS, NUM_ACTIONS, NUM_FINE_ACTIONS, SENSITIVITY  # noqa: F401

CONTACT_FORCE = 100.0
CONTACT_MARGIN = 1e-3
# action_space "fine": actions 5..8 push as 1..4 do at a quarter of the force. From rest one
# full push moves an agent's resting point by 0.2 (SENSITIVITY / MASS x DT^2 / DAMPING), so
# with the paper's five an agent at rest parks only on a lattice of side 0.2 round where it
# stopped, up to 0.141 from a target, and holds a point in between only by alternating pushes
# (docs/SWARM.md, "An agent at rest parks only on a lattice"); a quarter push moves it by 0.05,
# so it can park within 0.035 of any point, inside formation's 0.05.
FINE = 0.25
ACTION_DIM = 2  # continuous actions: one force command u per axis
CUTOFF_MARGINS = 20.0  # contact force treated as 0 beyond dist_min + 20 contact margins
ACTION_MEANINGS = ("noop", "-x", "+x", "-y", "+y", "-x/4", "+x/4", "-y/4", "+y/4")  # "discrete": the first 5


def num_actions(action_space: str) -> int:
    """Discrete actions per agent of an action space (continuous: 0, none)."""
    return {"discrete": NUM_ACTIONS, "fine": NUM_FINE_ACTIONS}.get(action_space, 0)


@ti.func
def action_force(a: ti.i32) -> ti.math.vec2:
    """Unit direction of discrete action a (0 no-op, 1 -x, 2 +x, 3 -y, 4 +y) times 5; actions
    5..8 ("fine") the directions of 1..4 at a quarter of that."""
    u = ti.math.vec2(0.0, 0.0)
    k = a
    strength = 1.0
    if a > NUM_ACTIONS - 1:
        k = a - (NUM_ACTIONS - 1)
        strength = FINE
    if k == 1:
        u[0] = -1.0
    elif k == 2:
        u[0] = 1.0
    elif k == 3:
        u[1] = -1.0
    elif k == 4:
        u[1] = 1.0
    return u * (strength * SENSITIVITY)


@ti.func
def continuous_force(u: ti.math.vec2) -> ti.math.vec2:
    """Force of continuous action u: 5 clip(u, -1, 1) per axis (MPE's continuous mode,
    with VMAS's clamp to the action range)."""
    return ti.math.clamp(u, -1.0, 1.0) * SENSITIVITY


@ti.func
def softplus(x: ti.f32) -> ti.f32:
    """log(1 + e^x), stable for large |x| (MPE uses np.logaddexp(0, x))."""
    return ti.max(x, 0.0) + ti.log(1.0 + ti.exp(-ti.abs(x)))


@ti.func
def contact_force(pa: ti.math.vec2, pb: ti.math.vec2, dist_min: ti.f32) -> ti.math.vec2:
    """Force on a from b: 100 (pa - pb)/d * k softplus(-(d - dist_min)/k)."""
    delta = pa - pb
    d2 = delta.dot(delta)
    f = ti.math.vec2(0.0, 0.0)
    # Beyond dist_min + 20 k the force is < 100 k e^-20 ~ 2e-10, far below float32
    # rounding of any velocity: skip the sqrt/exp/log (most pairs are far apart).
    # NOTE: MPE divides by zero (NaN) for coincident agents; we apply no force.
    reach = dist_min + CUTOFF_MARGINS * CONTACT_MARGIN
    if d2 > 0.0 and d2 < reach * reach:
        d = ti.sqrt(d2)
        pen = CONTACT_MARGIN * softplus(-(d - dist_min) / CONTACT_MARGIN)
        f = CONTACT_FORCE * delta / d * pen
    return f


@ti.func
def integrate_velocity(v: ti.math.vec2, force: ti.math.vec2) -> ti.math.vec2:
    return v * (1.0 - DAMPING) + (force / MASS) * DT

"""MPE world physics (Lowe et al. 2017, multiagent/core.py), per agent.

See docs/PAPER.md section 1. One step: action force (discrete, the paper's; or
continuous, MPE's continuous mode: 5 clip(u, -1, 1) per axis),
pairwise contact forces between agents, then semi-implicit Euler
    v <- v (1 - damping);  v <- v + F/m dt;  p <- p + v dt.
"""

import taichi as ti

DT = 0.1
DAMPING = 0.25
MASS = 1.0
SENSITIVITY = 5.0  # MPE's agent.accel default (discrete and continuous actions alike)
CONTACT_FORCE = 100.0
CONTACT_MARGIN = 1e-3
NUM_ACTIONS = 5
ACTION_DIM = 2  # continuous actions: one force command u per axis
ACTION_SPACES = ("discrete", "continuous")
CUTOFF_MARGINS = 20.0  # contact force treated as 0 beyond dist_min + 20 contact margins
ACTION_MEANINGS = ("noop", "-x", "+x", "-y", "+y")


@ti.func
def action_force(a: ti.i32) -> ti.math.vec2:
    """Unit direction of discrete action a (0 no-op, 1 -x, 2 +x, 3 -y, 4 +y) times 5."""
    u = ti.math.vec2(0.0, 0.0)
    if a == 1:
        u[0] = -1.0
    elif a == 2:
        u[0] = 1.0
    elif a == 3:
        u[1] = -1.0
    elif a == 4:
        u[1] = 1.0
    return u * SENSITIVITY


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

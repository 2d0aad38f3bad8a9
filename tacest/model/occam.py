"""The Occam term of pose-observed trajectories (2-D): the marginal likelihood's price of
the freedom a light object has to follow the pose noise.  See :func:`pose_occam` and
docs/estimation.md, "Pose observations and light objects"."""

from __future__ import annotations

import casadi as ca


#: Newton steps of pose_occam's innovation equation: from its two asymptotes, 4 steps
#: solve it to machine precision for every tracking index in [1e-8, 1e6]
OCCAM_NEWTON_STEPS = 4


def pose_occam(log_lam):
    """Occam term (dimensionless) of one pose-observed degree of freedom per sample.

    The loss fits each run's trajectory jointly with the parameters (a MAP of the
    latent trajectory), which is biased where the parameters set how freely the
    trajectory may move: the dynamics residual costs an object of mass m a velocity
    change w with sd s = sigma_v m_ref / m, so a light object follows the pose noise
    at no cost (docs/estimation.md, "Pose observations and light objects").  The
    marginal likelihood of the pose observations, with the trajectory integrated out,
    carries the missing term.  For a body moving freely (implicit Euler,
    q_t = q_(t-1) + dt v_t, v_t = v_(t-1) + w_t), observed with noise sigma_p at every
    sample, it is exact in the steady state of the Kalman filter: per sample
    0.5 log(S / sigma_p²), S the innovation variance.  With the tracking index
    lam = s dt / sigma_p and a = S / sigma_p² - 1, the Riccati equation reduces to
    a⁴ = lam² (a + 1) (a + 2)², solved here by Newton steps in log a.

    log_lam : log of the tracking index.  Returns 0.5 log(1 + a): ≈ (lam / 2)^½ for a
    heavy body (physics tighter than the data), ≈ log lam for a light one (the data
    resolve each velocity change: the object pays for the freedom it uses).
    """
    lam = ca.exp(log_lam)
    u = ca.log(ca.sqrt(2 * lam) + lam * lam)  # asymptotes: a ≈ sqrt(2 lam), a ≈ lam²
    for _ in range(OCCAM_NEWTON_STEPS):
        a = ca.exp(u)
        f = 2 * u - ca.log(a + 2) - 0.5 * ca.log1p(a) - log_lam
        u = u - f / (2 - a / (a + 2) - 0.5 * a / (a + 1))
    return 0.5 * ca.log1p(ca.exp(u))


#: free-direction weights of the Occam term (occam_free_weights): a contact row of
#: weight s takes a direction's freedom to OCCAM_HELD_EPS / (s + OCCAM_HELD_EPS), 3 % for
#: a touching contact (s = 1)
OCCAM_HELD_EPS = 0.03
#: sharpness of a ground vertex's touch weight exp(-OCCAM_TOUCH_SHARPNESS x (gap in
#: sig_gap - 1)+): 1 within one sig_gap of the ground, 0.05 at two, 0.0025 at three, so
#: that a vertex off the ground holds nothing
OCCAM_TOUCH_SHARPNESS = 3.0


def occam_free_weights(rows, weights, half_length):
    """Per-degree-of-freedom freedom (3,) of the object at one sample, for the Occam term.

    The Occam term (pose_occam) prices the freedom of a body that moves by process noise
    alone.  A direction held by a contact is not free: there the contact impulse, not the
    mass, absorbs any velocity change, so the mass does not set how freely it moves (a box
    resting on a face is held in height and angle whatever its mass; a finger pushing it
    holds it along the push).  Counting such directions as free prices light objects
    wrongly and pulled slow sliding pushes to twice their mass (docs/estimation.md).

    rows : list of (normal (2,) world, lever (2,) world m) of the contacts; weights :
    list of their weights in [0, 1] (a ground vertex's touch, a finger's flag);
    half_length : m, the length that puts the angle in length units (L/2, as the
    dynamics residual).  Each contact constrains the generalized direction
    a = [n_x, n_y, (r × n) / half_length]; with A = Σ s a aᵀ the freedom of degree j is
    the diagonal of ε (A + ε I)⁻¹ (ε = OCCAM_HELD_EPS): 1 where nothing holds it,
    ε / (s + ε) along a held axis.  Smooth in the contact weights and geometry."""
    A = OCCAM_HELD_EPS * ca.SX.eye(3)
    for (n, r), w in zip(rows, weights):
        a = ca.vertcat(n[0], n[1], (r[0] * n[1] - r[1] * n[0]) / half_length)
        A = A + w * (a @ a.T)
    return OCCAM_HELD_EPS * ca.diag(ca.inv(A))

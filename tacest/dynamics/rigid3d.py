"""Spatial rigid-body and contact terms (CasADi), the model of the 3-D estimator and of
its forward simulator.

Conventions (SPEC): world frame with gravity along -z; pose = [p (3), q (4)]: centre
of mass p (m, world) and unit quaternion q = [qw, qx, qy, qz] (scalar first, body to
world).  The estimator's velocity is [v (3), omega_b (3)]: world-frame COM velocity
(m/s) and the *body-frame* angular rate (rad/s); estimate files store the world-frame
rate omega_w = R(q) omega_b (SPEC).  Impulses are over one sample interval (t-1, t], N·s.

Time stepping (Anitescu 2006, implicit in the contact geometry; eq. numbers as in
docs/estimation3d.md)::

    m (v[t] - v[t-1])          = m g dt + sum_c lambda_c                          (D1a)
    I (w[t] - w[t-1]) + dt w[t] x I w[t] = sum_c r_c x R(q[t])^T lambda_c          (D1b)
    p[t] = p[t-1] + dt v[t]                                                      (D2a)
    q[t] = q[t-1] ⊗ exp(w[t] dt / 2)                                             (D2b)
    0 <= lambda_n ⟂ phi(q[t]) >= 0,  |lambda_t| <= mu lambda_n (second-order cone)  (C1, C2)
    lambda_t = -mu lambda_n s / |s| (maximal dissipation, s = slip velocity)       (C3)

with w = omega_b, r_c the contact point in the body frame and I the body-frame inertia
about the COM.  (D2b) is the exact update for a constant body rate over the interval;
the exponential is evaluated by its Taylor series in theta² = (|w| dt / 2)² (exact
derivatives everywhere, including w = 0) and normalised, so |q| is preserved exactly;
the series error is below 1e-10 for |w| dt <= 1 rad (147 rad/s at dt = 6.8 ms).

Inertia (physically valid by construction): the second-moment matrix
Sigma = ∫ r rᵀ dm (about the COM) is parameterized by its log-Cholesky factor,
Sigma = m L² C Cᵀ with C lower-triangular, C_ii = exp(a_i), C_ij = b_ij; the inertia is
I = tr(Sigma) 1 - Sigma.  Sigma ≻ 0 for every parameter value, which is the condition
for a rigid body with its COM at the origin (the pseudo-inertia matrix diag(Sigma, m) ≻ 0,
Wensing et al. 2018); it makes I positive definite and strictly satisfy the triangle
inequalities I_1 + I_2 > I_3 (I_1 + I_2 - I_3 = 2 sigma_3 in principal axes).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from tacest.errors import TacestError

#: number of terms of the Taylor series of cos(theta) and sin(theta)/theta in u = theta²
#: (through u⁵, i.e. theta^10: the first omitted term is theta^12 / 12! < 2e-9 theta^12)
_EXP_TERMS = 6


# ---------------------------------------------------------------------------------
# quaternions (CasADi; also accept numpy through DM)


def qmul(a, b):
    """Hamilton product a ⊗ b of two quaternions (4,), scalar first."""
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    return ca.vertcat(aw * bw - ax * bx - ay * by - az * bz,
                      aw * bx + ax * bw + ay * bz - az * by,
                      aw * by - ax * bz + ay * bw + az * bx,
                      aw * bz + ax * by - ay * bx + az * bw)


def qconj(q):
    """Conjugate [w, -x, -y, -z] (4,)."""
    return ca.vertcat(q[0], -q[1], -q[2], -q[3])


def qexp_half(w, dt):
    """exp(w dt / 2) as a unit quaternion (4,) for a body rate w (3,) rad/s over dt s.

    [cos theta, sin(theta)/theta · w dt/2] with theta = |w| dt / 2, by the Taylor
    series in theta² (smooth at w = 0), normalised to unit length.
    """
    h = w * (dt / 2)
    u = ca.dot(h, h)
    c, s = 0, 0
    fc, fs = 1.0, 1.0  # (2k)!, (2k+1)!
    for k in range(_EXP_TERMS):
        if k:
            fc *= (2 * k - 1) * (2 * k)
            fs *= (2 * k) * (2 * k + 1)
        c = c + (-1) ** k * u ** k / fc
        s = s + (-1) ** k * u ** k / fs
    e = ca.vertcat(c, s * h)
    return e / ca.sqrt(c * c + s * s * u)


def quat_rotation(q):
    """Rotation matrix (3, 3) of a nonzero quaternion (4,), not necessarily unit: the
    homogeneous form divided by |q|², exact for any scaling of q."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    n2 = w * w + x * x + y * y + z * z
    R = ca.vertcat(
        ca.horzcat(w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)),
        ca.horzcat(2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)),
        ca.horzcat(2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z))
    return R / n2


def quat_error_vector(q_obs, q):
    """Small-angle orientation error (3,) rad of q against q_obs: 2 vec(q_obs* ⊗ q),
    the rotation vector of the body-frame error for small errors (same hemisphere)."""
    d = qmul(qconj(q_obs), q)
    return 2 * d[1:4]


def cross(a, b):
    return ca.vertcat(a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


# ---------------------------------------------------------------------------------
# inertia


def inertia_from_cholesky(c):
    """(I (3, 3), Sigma (3, 3)) in units of m L² from log-Cholesky parameters
    c = [a1, a2, a3, b21, b31, b32] (see module docstring).  CasADi or numpy."""
    C = ca.vertcat(ca.horzcat(ca.exp(c[0]), 0, 0),
                   ca.horzcat(c[3], ca.exp(c[1]), 0),
                   ca.horzcat(c[4], c[5], ca.exp(c[2])))
    S = ca.mtimes(C, C.T)
    I_ = ca.trace(S) * ca.DM.eye(3) - S
    return I_, S


def cholesky_from_inertia(inertia) -> np.ndarray:
    """Inverse of :func:`inertia_from_cholesky` (numpy): the 6 parameters of a valid
    inertia (3, 3) given in units of m L².  Raises TacestError when the inertia is not
    physically valid (Sigma = tr(I)/2 · 1 - I not positive definite)."""
    I_ = np.asarray(inertia, float)
    I_ = 0.5 * (I_ + I_.T)
    S = 0.5 * np.trace(I_) * np.eye(3) - I_
    try:
        C = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise TacestError("inertia is not physically valid (it breaks a triangle inequality or is not "
                          "positive definite)") from None
    return np.array([np.log(C[0, 0]), np.log(C[1, 1]), np.log(C[2, 2]), C[1, 0], C[2, 0], C[2, 1]])


def inertia_numeric(c) -> np.ndarray:
    """(3, 3) numpy value of :func:`inertia_from_cholesky` (units of m L²)."""
    return np.array(ca.DM(inertia_from_cholesky(ca.DM(np.asarray(c, float)))[0]))


def second_moment_from_inertia(inertia) -> np.ndarray:
    """Sigma = tr(I)/2 · 1 - I (3, 3), same units as the inertia."""
    I_ = np.asarray(inertia, float)
    return 0.5 * np.trace(I_) * np.eye(3) - I_


# ---------------------------------------------------------------------------------
# ground contact


def ground_contacts(p, q, v, w, V_body, n_ground, h_ground):
    """Per-vertex ground contact quantities at the pose (p, q) and velocity (v, w).

    Parameters
    ----------
    p : (3,) m, world;  q : (4,) quaternion;  v : (3,) m/s world;  w : (3,) rad/s body
    V_body : (K, 3) vertices, body frame, m
    n_ground : (3,) unit ground normal (world);  h_ground : ground height along n, m

    Returns
    -------
    phi : list of K gaps, m (C1);  slip : list of K (3,) tangential velocities, m/s,
    world;  levers : list of K (3,) body-frame contact points, m;  R : (3, 3).
    """
    R = quat_rotation(q)
    phi, slip, levers = [], [], []
    for k in range(V_body.shape[0]):
        r_b = V_body[k, :].T
        pw = p + ca.mtimes(R, r_b)
        u = v + ca.mtimes(R, cross(w, r_b))
        phi.append(ca.dot(n_ground, pw) - h_ground)
        slip.append(u - ca.dot(n_ground, u) * n_ground)
        levers.append(r_b)
    return phi, slip, levers, R


# ---------------------------------------------------------------------------------
# numpy helpers shared by the estimator's initial guess and the simulator


def quat_log_rate(q_prev, q_next, dt) -> np.ndarray:
    """Body rate (3,) rad/s that takes unit q_prev to q_next in dt by (D2b):
    w = 2 log(q_prev* ⊗ q_next) / dt, on the short arc."""
    from tacest.geometry.transforms import quat_conjugate, quat_multiply

    d = quat_multiply(quat_conjugate(np.asarray(q_prev, float)), np.asarray(q_next, float))
    if d[0] < 0:
        d = -d
    s = np.linalg.norm(d[1:])
    if s < 1e-15:
        return np.zeros(3)
    angle = 2.0 * np.arctan2(s, d[0])
    return d[1:] / s * angle / dt


def align_quaternion_signs(Q) -> np.ndarray:
    """(T, 4) quaternions with signs flipped so that consecutive ones lie in the same
    hemisphere (q and -q are the same rotation); NaN rows are skipped."""
    Q = np.array(Q, float)
    last = None
    for t in range(Q.shape[0]):
        if not np.all(np.isfinite(Q[t])):
            continue
        if last is not None and np.dot(Q[t], last) < 0:
            Q[t] = -Q[t]
        last = Q[t]
    return Q

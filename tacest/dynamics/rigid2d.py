"""Planar rigid-body and contact terms (CasADi), the model every estimator stage uses.

Conventions (SPEC): world frame with gravity along -y; pose q = [x, y, angle] of the
centre of mass (angle CCW, body to world); velocity v = [vx, vy, omega] (world-frame
COM velocity, angular rate).  Impulses are over one sample interval (t-1, t], N·s.

Time stepping (Anitescu 2006, implicit in the contact geometry)::

    M (v[t] - v[t-1]) = dt f_ext + sum_c J_c(q[t])^T lambda_c[t]      (eq. D1)
    q[t] = q[t-1] + dt v[t]                                            (eq. D2)
    0 <= lambda_n ⟂ phi(q[t]) >= 0,   |lambda_t| <= mu lambda_n        (eq. C1, C2)
    lambda_t minimises lambda_t · s (maximal dissipation), s = slip velocity  (eq. C3)
"""

from __future__ import annotations

import casadi as ca

from tacest.geometry.shapes import cross2, rot2


def perp(n):
    """Tangent of a 2-D unit normal: n rotated by -90° (for the ground's up normal
    (0, 1) this is (1, 0), the +x direction)."""
    return ca.vertcat(n[1], -n[0])


def point_velocity(v, r_world):
    """Velocity (2,) of a body point at lever r_world (2,) from the COM: v_lin + ω × r."""
    return v[0:2] + v[2] * ca.vertcat(-r_world[1], r_world[0])


def generalized_impulse(r_world, impulse_world):
    """Generalized impulse (3,) [p_x, p_y, angular] of a world impulse (2,) applied at
    lever r_world (2,) from the COM: J^T lambda in eq. D1."""
    return ca.vertcat(impulse_world, cross2(r_world, impulse_world))


def ground_contacts(q, v, V_body, n_ground, h_ground):
    """Per-vertex ground contact quantities.

    Parameters
    ----------
    q, v : (3,) pose and velocity
    V_body : (K, 2) vertices, body frame, m
    n_ground : (2,) unit ground normal (world);  h_ground : ground height along n, m

    Returns
    -------
    phi : list of K gaps, m (eq. C1);  slip : list of K tangential velocities, m/s;
    levers : list of K (2,) levers r_world, m.
    """
    R = rot2(q[2])
    t_ground = perp(n_ground)
    phi, slip, levers = [], [], []
    for k in range(V_body.shape[0]):
        r = R @ V_body[k, :].T
        p = q[0:2] + r
        phi.append(ca.dot(n_ground, p) - h_ground)
        slip.append(ca.dot(t_ground, point_velocity(v, r)))
        levers.append(r)
    return phi, slip, levers


def mass_matrix_diag(mass, inertia):
    """Diagonal of the planar mass matrix M = diag(m, m, I)."""
    return ca.vertcat(mass, mass, inertia)

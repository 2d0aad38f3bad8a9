"""A fast forward model of the 3-D world for many box hypotheses at once (numpy).

The 3-D counterpart of tacest.model.forward2d: N hypotheses of one object, each a box
with its own extents, mass, inertia (uniform density) and frictions, moved in lockstep
under the measured fingertip motion: rigid bodies on a ground plane, explicit time
stepping (semi-implicit Euler, body rates, quaternions) with stiff penalty contacts at
the box's eight corners (spring and damper along the normal, regularized Coulomb
friction in the tangent plane), the fingertips either kinematic spheres that push by
penetration (with a drive's force limit) or, where the run measures forces, the
measured force applied at the measured contact point.  It is not the estimator's model
(tacest.model.stage3d): it is a cheap, robust simulator that follows a box through
slides, tips, topples and flights, so that a sampler (tacest.estimation.smc3d) can find
the basin the NLP then refines.  Other convex shapes are sampled as the box of their
extents, as the push tracker does (tacest.estimation.initial3d).

Units SI, world frame; the ground is {x : x·n_g = h}.  Arrays carry the hypotheses on
the first axis: half extents (N, 3) m (body frame, origin at the COM), position (N, 3)
m, quaternion (N, 4) [w, x, y, z] body to world, velocity (N, 3) m/s world, body rate
(N, 3) rad/s in the body frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# the contact constants are forward2d's: the same springs, damping and regularization
# hold a box in 3-D as a polygon in 2-D (GROUND_SINK per corner under a quarter of the
# weight instead of half)
from tacest.geometry.transforms import cross3, quat_from_rotvec, quat_multiply, quat_to_matrix
from tacest.model.forward2d import (DAMPING_RATIO, FINGER_FORCE_LIMIT, FINGER_STIFFNESS, GROUND_SINK, MAX_STEP,
                                    SLIP_REGULARIZATION)

__all__ = ["Boxes", "World3D", "box_finger_geometry", "GROUND_SINK", "MAX_STEP"]

#: the eight corners of the unit box, signs (8, 3)
CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)


@dataclass
class Boxes:
    """N box hypotheses: half extents (N, 3) m, mass (N,) kg, mu_ground (N,),
    mu_finger (N,); principal inertia (N, 3) kg·m² of a uniform box."""

    half: np.ndarray
    mass: np.ndarray
    mu_ground: np.ndarray
    mu_finger: np.ndarray

    @property
    def inertia(self) -> np.ndarray:
        e2 = (2.0 * self.half) ** 2
        return self.mass[:, None] * (e2[:, [1, 0, 0]] + e2[:, [2, 2, 1]]) / 12.0

    @property
    def corners(self) -> np.ndarray:
        """(N, 8, 3) m body frame."""
        return self.half[:, None, :] * CORNER_SIGNS[None]


def _turned(q, phi):
    """q ⊗ exp(phi / 2), renormalised: quaternions (N, 4) turned by body-frame rotation
    vectors phi (N, 3) rad."""
    out = quat_multiply(q, quat_from_rotvec(phi))
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def box_finger_geometry(half, R, position, centre__world):
    """Signed distance (N,) m of a point centre__world (3,) to each box (negative
    inside), the outward normal (N, 3) world there, and the closest surface point
    (N, 3) world.  half (N, 3) m, R (N, 3, 3) body to world, position (N, 3) m."""
    c_b = np.einsum("nji,nj->ni", R, centre__world[None, :] - position)
    q = np.abs(c_b) - half
    outside = np.maximum(q, 0.0)
    d_out = np.linalg.norm(outside, axis=1)
    k = np.argmax(q, axis=1)
    rows = np.arange(len(k))
    n_in = np.zeros_like(c_b)
    n_in[rows, k] = np.where(c_b[rows, k] >= 0, 1.0, -1.0)
    n_out = np.sign(c_b) * outside / np.maximum(d_out, 1e-12)[:, None]
    is_out = d_out > 1e-12
    n_b = np.where(is_out[:, None], n_out, n_in)
    sd = np.where(is_out, d_out, q[rows, k])
    point_b = c_b - sd[:, None] * n_b
    return sd, np.einsum("nij,nj->ni", R, n_b), np.einsum("nij,nj->ni", R, point_b) + position


class World3D:
    """The forward model of one run's ground and gravity for N box hypotheses.

    up : (3,) unit ground normal; ground_height : m; gravity : (3,) m/s² world;
    finger_radius : (F,) m.
    """

    def __init__(self, up, ground_height, gravity, finger_radius):
        self.n_g = np.asarray(up, float) / np.linalg.norm(up)
        self.h = float(ground_height)
        self.g = np.asarray(gravity, float)
        self.g_mag = float(np.linalg.norm(self.g))
        self.radius = np.asarray(finger_radius, float)

    def rest_position(self, half, R, position):
        """(N, 3) positions moved along up so that each box (half extents (N, 3) m,
        orientation R (N, 3, 3)) rests on the ground, sunk by GROUND_SINK."""
        low = np.min(np.einsum("nij,nkj->nki", R, half[:, None, :] * CORNER_SIGNS[None]) @ self.n_g, axis=1)
        height = position @ self.n_g - self.h
        return position + (-low - GROUND_SINK - height)[:, None] * self.n_g[None]

    def step(self, hyp: Boxes, pos, quat, vel, omega_b, h, fingers=(), forces=()):
        """Advance the state (pos, quat, vel, omega_b) by h s under gravity, the ground
        and the fingertips: ``fingers`` [(finger index, centre (3,) m, velocity (3,)
        m/s)] kinematic spheres pushing by penetration; ``forces`` [(point (3,) m, force
        (3,) N)] applied to every hypothesis as measured.  Returns the new state and the
        fingers' forces on the object [(N, 3) N] in the order of ``fingers``."""
        m, I = hyp.mass, hyp.inertia
        R = quat_to_matrix(quat)
        omega_w = np.einsum("nij,nj->ni", R, omega_b)
        lever = np.einsum("nij,nkj->nki", R, hyp.corners)  # (N, 8, 3) COM to corner, world
        phi = (lever + pos[:, None]) @ self.n_g - self.h
        pen = np.maximum(-phi, 0.0)
        vv = vel[:, None] + cross3(omega_w[:, None], lever)
        vn = vv @ self.n_g
        vt = vv - vn[..., None] * self.n_g
        k = (m * self.g_mag / (4 * GROUND_SINK))[:, None]
        c = 2 * DAMPING_RATIO * np.sqrt(k * m[:, None] / 4)
        fn = np.where(pen > 0, np.maximum(k * pen - c * vn, 0.0), 0.0)
        speed = np.sqrt(np.sum(vt * vt, axis=-1) + SLIP_REGULARIZATION ** 2)
        F_k = fn[..., None] * self.n_g - (hyp.mu_ground[:, None] * fn / speed)[..., None] * vt
        force = F_k.sum(1)
        torque = cross3(lever, F_k).sum(1)
        out = []
        for f, centre, v_f in fingers:
            sd, n_w, point = box_finger_geometry(hyp.half, R, pos, np.asarray(centre, float))
            depth = self.radius[f] - sd
            r = point - pos
            rel = np.asarray(v_f, float)[None] - (vel + cross3(omega_w, r))
            closing = -np.sum(rel * n_w, axis=1)
            cf = 2 * DAMPING_RATIO * np.sqrt(FINGER_STIFFNESS * m)
            f_n = np.where(depth > 0, np.clip(FINGER_STIFFNESS * depth + cf * closing, 0.0, FINGER_FORCE_LIMIT), 0.0)
            slip = rel - np.sum(rel * n_w, axis=1, keepdims=True) * n_w
            f_t = (hyp.mu_finger * f_n / np.sqrt(np.sum(slip * slip, 1) + SLIP_REGULARIZATION ** 2))[:, None] * slip
            F = -f_n[:, None] * n_w + f_t
            force = force + F
            torque = torque + cross3(r, F)
            out.append(F)
        for point, F_meas in forces:
            r = np.asarray(point, float)[None] - pos
            F = np.broadcast_to(np.asarray(F_meas, float), r.shape)
            force = force + F
            torque = torque + cross3(r, F)
        tau_b = np.einsum("nji,nj->ni", R, torque)
        omega_b = omega_b + h * (tau_b - cross3(omega_b, I * omega_b)) / I
        vel = vel + h * (force / m[:, None] + self.g)
        pos = pos + h * vel
        quat = _turned(quat, h * omega_b)
        return pos, quat, vel, omega_b, out

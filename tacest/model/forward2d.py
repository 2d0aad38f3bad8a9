"""A fast forward model of the 2-D world for many object hypotheses at once (numpy).

N hypotheses (particles) of one object, each a convex polygon with its own vertices,
mass, inertia and frictions, are moved in lockstep under the measured fingertip motion:
rigid bodies on a ground plane, explicit time stepping (semi-implicit Euler) with stiff
penalty contacts (spring and damper along the normal, regularized Coulomb friction along
the tangent), the fingertips either kinematic spheres that push by penetration (with the
force limit of a real drive) or, where the run measures forces, the measured force
applied at the measured contact point.  It is not the estimator's model (that is
tacest.model.stage2d): it is a cheap, robust simulator that can follow an object through
slides, tips, topples and flights, so that a sampler (tacest.estimation.smc2d) can find
the basin the NLP then refines.

Units SI, world frame; the ground is {x : x·n_g = h}.  Arrays carry the hypotheses on
the first axis: vertices (N, K, 2) m body frame (origin at the COM), pose (N, 3)
[x, y, angle], velocity (N, 3) [vx, vy, omega].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: m, penetration of a ground vertex under half the object's weight: the ground's
#: spring per vertex is m·g / (2 GROUND_SINK), so a box at rest on a face sinks this far
#: (the NLP refines the pose; stiffer springs need smaller time steps)
GROUND_SINK = 1e-3
#: fraction of critical damping of the ground and finger springs
DAMPING_RATIO = 1.0
#: m/s, slip speed below which Coulomb friction is regularized (a sticking object creeps
#: at most about this fast under a push near the cone's limit)
SLIP_REGULARIZATION = 0.01
#: N/m, stiffness of a kinematic fingertip's penalty contact: 20 N per mm of penetration
FINGER_STIFFNESS = 2.0e4
#: N, force limit of a fingertip (the simulators' drives push up to 30 N)
FINGER_FORCE_LIMIT = 30.0
#: s, longest time step: stable for the ground and finger springs above with objects of
#: 50 g and more (h·sqrt(k/m) <= 0.7)
MAX_STEP = 1e-3


@dataclass
class Hypotheses:
    """N object hypotheses: vertices (N, K, 2) m (body frame, CCW, COM at the origin),
    mass (N,) kg, inertia (N,) kg·m² about the COM, mu_ground (N,), mu_finger (N,)."""

    vertices: np.ndarray
    mass: np.ndarray
    inertia: np.ndarray
    mu_ground: np.ndarray
    mu_finger: np.ndarray

    def take(self, idx) -> "Hypotheses":
        return Hypotheses(self.vertices[idx], self.mass[idx], self.inertia[idx], self.mu_ground[idx],
                          self.mu_finger[idx])


def box_hypotheses(width, height, mass, mu_ground, mu_finger) -> Hypotheses:
    """Boxes of uniform density (all (N,) arrays, m, kg)."""
    w, h = np.asarray(width, float) / 2, np.asarray(height, float) / 2
    V = np.stack([np.stack([-w, -h], -1), np.stack([w, -h], -1), np.stack([w, h], -1), np.stack([-w, h], -1)], 1)
    m = np.asarray(mass, float)
    return Hypotheses(V, m, m * (4 * w * w + 4 * h * h) / 12, np.asarray(mu_ground, float),
                      np.asarray(mu_finger, float))


def rotations(angle) -> np.ndarray:
    """(N, 2, 2) rotation matrices (body to world) of angles (N,) rad."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _perp(r):
    """(..., 2) the vectors r rotated by +90°: ω × r = ω · perp(r)."""
    return np.stack([-r[..., 1], r[..., 0]], -1)


def finger_geometry(vertices, pose, centre__world):
    """Signed distance (N,) m of a point (2,) to each hypothesis' boundary (negative
    inside), the outward normal (N, 2) world at its closest boundary point, and that
    point (N, 2) world."""
    R = rotations(pose[:, 2])
    c_b = np.einsum("nji,nj->ni", R, centre__world[None, :] - pose[:, :2])  # body frame
    a = vertices
    b = np.roll(vertices, -1, axis=1)
    e = b - a  # (N, K, 2)
    t = np.clip(np.einsum("nkj,nkj->nk", c_b[:, None] - a, e) / np.einsum("nkj,nkj->nk", e, e), 0.0, 1.0)
    closest = a + t[..., None] * e
    diff = c_b[:, None] - closest
    dist = np.sqrt(np.einsum("nkj,nkj->nk", diff, diff))
    k = np.argmin(dist, axis=1)
    rows = np.arange(len(k))
    n_edge = np.stack([e[..., 1], -e[..., 0]], -1) / np.linalg.norm(e, axis=-1, keepdims=True)  # outward (CCW)
    inside = np.all(np.einsum("nkj,nkj->nk", c_b[:, None] - a, n_edge) <= 0, axis=1)
    d_min = dist[rows, k]
    normal_b = np.where((inside | (d_min < 1e-12))[:, None], n_edge[rows, k],
                        diff[rows, k] / np.maximum(d_min, 1e-12)[:, None])
    sd = np.where(inside, -d_min, d_min)
    normal_w = np.einsum("nij,nj->ni", R, normal_b)
    point_w = np.einsum("nij,nj->ni", R, closest[rows, k]) + pose[:, :2]
    return sd, normal_w, point_w


class World2D:
    """The forward model of one run's ground and gravity for N hypotheses.

    up : (2,) unit ground normal; ground_height : m; gravity : (2,) m/s² world;
    finger_radius : (F,) m.
    """

    def __init__(self, up, ground_height, gravity, finger_radius):
        self.n_g = np.asarray(up, float) / np.linalg.norm(up)
        self.t_g = np.array([self.n_g[1], -self.n_g[0]])
        self.h = float(ground_height)
        self.g = np.asarray(gravity, float)
        self.g_mag = float(np.linalg.norm(self.g))
        self.radius = np.asarray(finger_radius, float)

    def rest_pose(self, vertices, x_along, angle=None):
        """(N, 3) poses of hypotheses resting on the ground at ``x_along`` (N,) m along
        it, sunk by their equilibrium penetration (GROUND_SINK)."""
        N = vertices.shape[0]
        ang = np.zeros(N) if angle is None else np.asarray(angle, float)
        R = rotations(ang)
        Vw = np.einsum("nij,nkj->nki", R, vertices)
        lowest = np.min(Vw @ self.n_g, axis=1)
        height = self.h - lowest - GROUND_SINK
        pos = x_along[:, None] * self.t_g[None] + height[:, None] * self.n_g[None]
        return np.concatenate([pos, ang[:, None]], 1)

    def step(self, hyp: Hypotheses, pose, vel, h, fingers=(), forces=()):
        """Advance (pose, velocity) by h s (semi-implicit Euler) under gravity, the
        ground, and the fingertips: ``fingers`` [(finger index, centre (2,) m, velocity
        (2,) m/s)] kinematic spheres pushing by penetration; ``forces`` [(point (2,) m,
        force (2,) N)] applied to every hypothesis as measured.  Returns the new (pose,
        vel) and the fingers' forces on the object [(N, 2) N] in the order of
        ``fingers``."""
        m, I = hyp.mass, hyp.inertia
        R = rotations(pose[:, 2])
        lever = np.einsum("nij,nkj->nki", R, hyp.vertices)  # (N, K, 2) COM to vertex, world
        Vw = lever + pose[:, None, :2]
        vv = vel[:, None, :2] + vel[:, None, 2:3] * _perp(lever)
        phi = Vw @ self.n_g - self.h
        pen = np.maximum(-phi, 0.0)
        vn = vv @ self.n_g
        vt = vv @ self.t_g
        k = (m * self.g_mag / (2 * GROUND_SINK))[:, None]
        c = 2 * DAMPING_RATIO * np.sqrt(k * m[:, None] / 2)
        fn = np.where(pen > 0, np.maximum(k * pen - c * vn, 0.0), 0.0)
        ft = -hyp.mu_ground[:, None] * fn * vt / np.sqrt(vt * vt + SLIP_REGULARIZATION ** 2)
        F_k = fn[..., None] * self.n_g + ft[..., None] * self.t_g  # (N, K, 2)
        force = F_k.sum(1)
        torque = np.sum(lever[..., 0] * F_k[..., 1] - lever[..., 1] * F_k[..., 0], axis=1)
        out = []
        for f, centre, v_f in fingers:
            sd, n_w, point = finger_geometry(hyp.vertices, pose, np.asarray(centre, float))
            depth = self.radius[f] - sd
            r = point - pose[:, :2]
            v_pt = vel[:, :2] + vel[:, 2:3] * _perp(r)
            rel = np.asarray(v_f, float)[None] - v_pt  # fingertip relative to the surface point
            closing = -np.sum(rel * n_w, axis=1)  # > 0 while the finger moves into the object
            kf = FINGER_STIFFNESS
            cf = 2 * DAMPING_RATIO * np.sqrt(kf * m)
            f_n = np.where(depth > 0, np.clip(kf * depth + cf * closing, 0.0, FINGER_FORCE_LIMIT), 0.0)
            t_w = _perp(n_w)
            slip = np.sum(rel * t_w, axis=1)
            f_t = hyp.mu_finger * f_n * slip / np.sqrt(slip * slip + SLIP_REGULARIZATION ** 2)
            F = -f_n[:, None] * n_w + f_t[:, None] * t_w
            force = force + F
            torque = torque + r[:, 0] * F[:, 1] - r[:, 1] * F[:, 0]
            out.append(F)
        for point, F_meas in forces:
            r = np.asarray(point, float)[None] - pose[:, :2]
            F = np.broadcast_to(np.asarray(F_meas, float), r.shape)
            force = force + F
            torque = torque + r[:, 0] * F[:, 1] - r[:, 1] * F[:, 0]
        vel = vel.copy()
        vel[:, :2] += h * (force / m[:, None] + self.g)
        vel[:, 2] += h * torque / I
        pose = pose + h * vel
        return pose, vel, out

"""A fast forward model of the 3-D world for many box hypotheses at once (compiled).

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
(N, 3) rad/s in the body frame.  The stepping is a numba kernel (one hypothesis at a
time, every substep of a sample in one call: :meth:`World3D.advance`); numpy over the
(N, 8, 3) corner arrays took ~0.7 ms per step and 62 % of a 3-D estimate's time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

# the contact constants are forward2d's: the same springs, damping and regularization
# hold a box in 3-D as a polygon in 2-D (GROUND_SINK per corner under a quarter of the
# weight instead of half)
from tacest.model.forward2d import (DAMPING_RATIO, FINGER_FORCE_LIMIT, FINGER_STIFFNESS, GROUND_SINK, MAX_STEP,
                                    SLIP_REGULARIZATION, kernel_drive)

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


# ---------------------------------------------------------------------------------
# the compiled kernel: one hypothesis at a time, every substep of a sample in one call


@njit(cache=True)
def _sign(x):
    return 1.0 if x > 0 else (-1.0 if x < 0 else 0.0)


@njit(cache=True)
def _rotation(q, R):
    """R (3, 3) ← body to world of the quaternion q (4,) [w, x, y, z], normalised first."""
    nq = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    w, x, y, z = q[0] / nq, q[1] / nq, q[2] / nq, q[3] / nq
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


@njit(cache=True)
def _turn(q, p0, p1, p2):
    """q (4,) ← q ⊗ exp(phi / 2), renormalised: turned by the body-frame rotation vector
    phi = (p0, p1, p2) rad."""
    a = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    s = math.sin(a / 2) / a if a > 1e-12 else 0.5
    bw, bx, by, bz = math.cos(a / 2), s * p0, s * p1, s * p2
    aw, ax, ay, az = q[0], q[1], q[2], q[3]
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    n = math.sqrt(w * w + x * x + y * y + z * z)
    q[0], q[1], q[2], q[3] = w / n, x / n, y / n, z / n


@njit(cache=True)
def _closest(half, R, position, centre, n_w, point):
    """Signed distance (m, negative inside) of the point ``centre`` (3,) to the box of
    half extents ``half`` (3,) at (R (3, 3), position (3,)); n_w (3,) ← the outward
    normal (world) there, point (3,) ← the closest surface point (world)."""
    c_b = np.empty(3)
    q = np.empty(3)
    n_b = np.zeros(3)
    d2 = 0.0
    for i in range(3):
        c_b[i] = (R[0, i] * (centre[0] - position[0]) + R[1, i] * (centre[1] - position[1])
                  + R[2, i] * (centre[2] - position[2]))
        q[i] = abs(c_b[i]) - half[i]
        if q[i] > 0:
            d2 += q[i] * q[i]
    d_out = math.sqrt(d2)
    if d_out > 1e-12:
        sd = d_out
        for i in range(3):
            n_b[i] = _sign(c_b[i]) * max(q[i], 0.0) / d_out
    else:
        k = 0
        for i in range(1, 3):
            if q[i] > q[k]:
                k = i
        sd = q[k]
        n_b[k] = 1.0 if c_b[k] >= 0 else -1.0
    for r in range(3):
        n_w[r] = R[r, 0] * n_b[0] + R[r, 1] * n_b[1] + R[r, 2] * n_b[2]
        point[r] = (R[r, 0] * (c_b[0] - sd * n_b[0]) + R[r, 1] * (c_b[1] - sd * n_b[1])
                    + R[r, 2] * (c_b[2] - sd * n_b[2]) + position[r])
    return sd


@njit(cache=True)
def _geometry(half, R, position, centre):
    n = half.shape[0]
    sd, n_w, point = np.empty(n), np.empty((n, 3)), np.empty((n, 3))
    for i in range(n):
        sd[i] = _closest(half[i], R[i], position[i], centre, n_w[i], point[i])
    return sd, n_w, point


@njit(cache=True)
def _advance(half, mass, inertia, mu_g, mu_f, pos, quat, vel, om, n_g, h_ground, g, g_mag, radius, finger, c0, c1,
             v_f, f_points, f_values, n_sub, h):
    """n_sub steps of h s for every hypothesis (Boxes' arrays, inertia (N, 3) principal),
    in place on pos, quat, vel, om (N, ...):
    kinematic fingertips ``finger`` (K,) (indices into radius) moving linearly from c0 to
    c1 (K, 3) at v_f (K, 3) over the substeps, measured forces f_values (M, 3) N at
    f_points (M, 3).  Returns the fingers' forces (N, K, 3) N of the last substep.
    Scalar code: small arrays allocated in the loop cost more than the arithmetic."""
    N, K, M = half.shape[0], finger.shape[0], f_points.shape[0]
    eps2 = SLIP_REGULARIZATION ** 2
    out = np.zeros((N, K, 3))
    R = np.empty((3, 3))
    lever = np.empty(3)
    centre = np.empty(3)
    n_w = np.empty(3)
    point = np.empty(3)
    for i in range(N):
        m = mass[i]
        I0, I1, I2 = inertia[i, 0], inertia[i, 1], inertia[i, 2]
        k_g = m * g_mag / (4 * GROUND_SINK)
        c_g = 2 * DAMPING_RATIO * math.sqrt(k_g * m / 4)
        c_f = 2 * DAMPING_RATIO * math.sqrt(FINGER_STIFFNESS * m)
        p, v, w = pos[i], vel[i], om[i]
        for j in range(n_sub):
            a = (j + 1) / n_sub
            _rotation(quat[i], R)
            ow0 = R[0, 0] * w[0] + R[0, 1] * w[1] + R[0, 2] * w[2]
            ow1 = R[1, 0] * w[0] + R[1, 1] * w[1] + R[1, 2] * w[2]
            ow2 = R[2, 0] * w[0] + R[2, 1] * w[1] + R[2, 2] * w[2]
            f0 = f1 = f2 = t0 = t1 = t2 = 0.0
            for c in range(8):
                for r in range(3):
                    lever[r] = (R[r, 0] * half[i, 0] * CORNER_SIGNS[c, 0] + R[r, 1] * half[i, 1] * CORNER_SIGNS[c, 1]
                                + R[r, 2] * half[i, 2] * CORNER_SIGNS[c, 2])
                pen = h_ground - ((lever[0] + p[0]) * n_g[0] + (lever[1] + p[1]) * n_g[1] + (lever[2] + p[2]) * n_g[2])
                if not pen > 0:  # NaN: no force, as off the ground
                    continue
                vv0 = v[0] + ow1 * lever[2] - ow2 * lever[1]
                vv1 = v[1] + ow2 * lever[0] - ow0 * lever[2]
                vv2 = v[2] + ow0 * lever[1] - ow1 * lever[0]
                vn = vv0 * n_g[0] + vv1 * n_g[1] + vv2 * n_g[2]
                vt0, vt1, vt2 = vv0 - vn * n_g[0], vv1 - vn * n_g[1], vv2 - vn * n_g[2]
                fn = max(k_g * pen - c_g * vn, 0.0)
                mu = mu_g[i] * fn / math.sqrt(vt0 * vt0 + vt1 * vt1 + vt2 * vt2 + eps2)
                F0, F1, F2 = fn * n_g[0] - mu * vt0, fn * n_g[1] - mu * vt1, fn * n_g[2] - mu * vt2
                f0, f1, f2 = f0 + F0, f1 + F1, f2 + F2
                t0 += lever[1] * F2 - lever[2] * F1
                t1 += lever[2] * F0 - lever[0] * F2
                t2 += lever[0] * F1 - lever[1] * F0
            for f in range(K):
                for r in range(3):
                    centre[r] = (1 - a) * c0[f, r] + a * c1[f, r]
                sd = _closest(half[i], R, p, centre, n_w, point)
                depth = radius[finger[f]] - sd
                if not depth > 0:  # NaN: no force, as out of reach
                    out[i, f, 0] = out[i, f, 1] = out[i, f, 2] = 0.0
                    continue
                r0, r1, r2 = point[0] - p[0], point[1] - p[1], point[2] - p[2]
                rel0 = v_f[f, 0] - (v[0] + ow1 * r2 - ow2 * r1)
                rel1 = v_f[f, 1] - (v[1] + ow2 * r0 - ow0 * r2)
                rel2 = v_f[f, 2] - (v[2] + ow0 * r1 - ow1 * r0)
                rn = rel0 * n_w[0] + rel1 * n_w[1] + rel2 * n_w[2]
                f_n = min(max(FINGER_STIFFNESS * depth - c_f * rn, 0.0), FINGER_FORCE_LIMIT)
                s0, s1, s2 = rel0 - rn * n_w[0], rel1 - rn * n_w[1], rel2 - rn * n_w[2]
                mu = mu_f[i] * f_n / math.sqrt(s0 * s0 + s1 * s1 + s2 * s2 + eps2)
                F0, F1, F2 = -f_n * n_w[0] + mu * s0, -f_n * n_w[1] + mu * s1, -f_n * n_w[2] + mu * s2
                out[i, f, 0], out[i, f, 1], out[i, f, 2] = F0, F1, F2
                f0, f1, f2 = f0 + F0, f1 + F1, f2 + F2
                t0 += r1 * F2 - r2 * F1
                t1 += r2 * F0 - r0 * F2
                t2 += r0 * F1 - r1 * F0
            for k in range(M):
                F0, F1, F2 = f_values[k, 0], f_values[k, 1], f_values[k, 2]
                r0, r1, r2 = f_points[k, 0] - p[0], f_points[k, 1] - p[1], f_points[k, 2] - p[2]
                f0, f1, f2 = f0 + F0, f1 + F1, f2 + F2
                t0 += r1 * F2 - r2 * F1
                t1 += r2 * F0 - r0 * F2
                t2 += r0 * F1 - r1 * F0
            # body torque Rᵀ τ; Euler's equations with the gyroscopic term ω × Iω
            tb0 = R[0, 0] * t0 + R[1, 0] * t1 + R[2, 0] * t2
            tb1 = R[0, 1] * t0 + R[1, 1] * t1 + R[2, 1] * t2
            tb2 = R[0, 2] * t0 + R[1, 2] * t1 + R[2, 2] * t2
            L0, L1, L2 = I0 * w[0], I1 * w[1], I2 * w[2]
            g0 = w[1] * L2 - w[2] * L1
            g1 = w[2] * L0 - w[0] * L2
            g2 = w[0] * L1 - w[1] * L0
            w[0] += h * (tb0 - g0) / I0
            w[1] += h * (tb1 - g1) / I1
            w[2] += h * (tb2 - g2) / I2
            v[0] += h * (f0 / m + g[0])
            v[1] += h * (f1 / m + g[1])
            v[2] += h * (f2 / m + g[2])
            p[0] += h * v[0]
            p[1] += h * v[1]
            p[2] += h * v[2]
            _turn(quat[i], h * w[0], h * w[1], h * w[2])
    return out


def box_finger_geometry(half, R, position, centre__world):
    """Signed distance (N,) m of a point centre__world (3,) to each box (negative
    inside), the outward normal (N, 3) world there, and the closest surface point
    (N, 3) world.  half (N, 3) m, R (N, 3, 3) body to world, position (N, 3) m."""
    half, R, position = (np.ascontiguousarray(a, float) for a in (half, R, position))
    n = half.shape[0]
    if half.shape != (n, 3) or R.shape != (n, 3, 3) or position.shape != (n, 3):
        raise ValueError(f"box_finger_geometry: half {half.shape}, R {R.shape}, position {position.shape} "
                         "are not (N, 3), (N, 3, 3), (N, 3)")  # the compiled kernel does not check
    return _geometry(half, R, position, np.asarray(centre__world, float).reshape(3))


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
        out = self.advance(hyp, pos, quat, vel, omega_b, h, 1, fingers=fingers, forces=forces)
        return (*out[:4], [out[4][:, k] for k in range(len(fingers))])

    def advance(self, hyp: Boxes, pos, quat, vel, omega_b, h, n_sub, fingers=(), start_centres=(), forces=()):
        """n_sub steps of h s (semi-implicit Euler, module docstring): ``fingers`` [(finger
        index, centre at the end (3,) m, velocity (3,) m/s)] move linearly from
        ``start_centres`` [(3,) m] (default: the end centres) to their end centres over
        the substeps (the k-th of n_sub at fraction k / n_sub); ``forces`` [(point (3,)
        m, force (3,) N)] act throughout.  Returns copies of the new state (pos, quat,
        vel, omega_b) and the fingers' forces (N, K, 3) N of the last substep."""
        drive = kernel_drive(fingers, start_centres, forces, 3, "World3D.advance")
        state = [np.array(a, float, order="C", copy=True) for a in (pos, quat, vel, omega_b)]
        n = hyp.half.shape[0]
        shapes = [a.shape for a in state] + [np.shape(a) for a in (hyp.half, hyp.mass, hyp.mu_ground, hyp.mu_finger)]
        if shapes != [(n, 3), (n, 4), (n, 3), (n, 3), (n, 3), (n,), (n,), (n,)]:
            raise ValueError(f"World3D.advance: hypotheses and state of other sizes {shapes}")  # the kernel does not check
        F = _advance(*(np.ascontiguousarray(a, float) for a in (hyp.half, hyp.mass, hyp.inertia, hyp.mu_ground,
                                                                 hyp.mu_finger)),
                     *state, self.n_g, self.h, self.g, self.g_mag, self.radius, *drive, int(n_sub), float(h))
        return (*state, F)

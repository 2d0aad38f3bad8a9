"""A fast forward model of the 2-D world for many object hypotheses at once (compiled).

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
[x, y, angle], velocity (N, 3) [vx, vy, omega].  The stepping is a numba kernel (one
hypothesis at a time, every substep of a sample in one call: :meth:`World2D.advance`),
as in tacest.model.forward3d; numpy over the (N, K) vertex arrays took ~0.3-1.2 ms per
step, about half of a 2-D estimate's time.
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np
from numba import njit

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

    def arrays(self) -> tuple:
        """(vertices, mass, inertia, mu_ground, mu_finger) as C-contiguous float arrays,
        checked for matching sizes (the compiled kernels do not check)."""
        V = np.ascontiguousarray(self.vertices, float)
        n = V.shape[0]
        rest = [np.ascontiguousarray(a, float) for a in (self.mass, self.inertia, self.mu_ground, self.mu_finger)]
        if V.ndim != 3 or V.shape[2] != 2 or V.shape[1] < 3 or any(a.shape != (n,) for a in rest):
            raise ValueError(f"Hypotheses: vertices {V.shape} and parameters {[a.shape for a in rest]} are not "
                             "(N, K >= 3, 2) and (N,)")
        return (V, *rest)


def box_hypotheses(width, height, mass, mu_ground, mu_finger) -> Hypotheses:
    """Boxes of uniform density (all (N,) arrays, m, kg)."""
    w, h = np.asarray(width, float) / 2, np.asarray(height, float) / 2
    V = np.stack([np.stack([-w, -h], -1), np.stack([w, -h], -1), np.stack([w, h], -1), np.stack([-w, h], -1)], 1)
    m = np.asarray(mass, float)
    return Hypotheses(V, m, m * (4 * w * w + 4 * h * h) / 12, np.asarray(mu_ground, float),
                      np.asarray(mu_finger, float))


# ---------------------------------------------------------------------------------
# the compiled kernels: one hypothesis at a time, every substep of a sample in one call


@njit(cache=True)
def _closest(V, c, s, px, py, cx, cy):
    """The point (cx, cy) m world against the polygon V (K, 2) m (body frame, CCW) at
    pose (px, py, angle with cos c and sin s): its signed distance (m, negative inside),
    the outward normal (world) at its closest boundary point, and that point (world),
    as (sd, nx, ny, qx, qy); all NaN for a point not finite."""
    if not (math.isfinite(cx) and math.isfinite(cy)):  # a fingertip not tracked: nowhere
        return math.nan, math.nan, math.nan, math.nan, math.nan
    dx, dy = cx - px, cy - py
    bx, by = c * dx + s * dy, c * dy - s * dx  # the point in the body frame
    K = V.shape[0]
    best = np.inf
    inside = True
    dbx = dby = nbx = nby = 0.0  # from the closest boundary point to the point; that edge's normal
    for k in range(K):
        ax, ay = V[k, 0], V[k, 1]
        k1 = k + 1 if k + 1 < K else 0
        ex, ey = V[k1, 0] - ax, V[k1, 1] - ay
        ee = ex * ex + ey * ey
        length = math.sqrt(ee)
        enx, eny = ey / length, -ex / length  # outward (CCW)
        rx, ry = bx - ax, by - ay
        if rx * enx + ry * eny > 0:
            inside = False
        t = min(max((rx * ex + ry * ey) / ee, 0.0), 1.0)
        qx, qy = rx - t * ex, ry - t * ey
        d2 = qx * qx + qy * qy
        if d2 < best:
            best, dbx, dby, nbx, nby = d2, qx, qy, enx, eny
    d = math.sqrt(best)
    if not (inside or d < 1e-12):
        nbx, nby = dbx / d, dby / d
    sd = -d if inside else d
    cbx, cby = bx - dbx, by - dby  # the closest boundary point, body frame
    return sd, c * nbx - s * nby, s * nbx + c * nby, c * cbx - s * cby + px, s * cbx + c * cby + py


@njit(cache=True)
def _geometry(V, pose, cx, cy):
    n = V.shape[0]
    sd, n_w, point = np.empty(n), np.empty((n, 2)), np.empty((n, 2))
    for i in range(n):
        c, s = math.cos(pose[i, 2]), math.sin(pose[i, 2])
        sd[i], n_w[i, 0], n_w[i, 1], point[i, 0], point[i, 1] = _closest(V[i], c, s, pose[i, 0], pose[i, 1], cx, cy)
    return sd, n_w, point


@njit(cache=True)
def _advance(V, mass, inertia, mu_g, mu_f, pose, vel, n_g, h_ground, g, g_mag, radius, finger, c0, c1, v_f,
             f_points, f_values, n_sub, h):
    """n_sub steps of h s for every hypothesis (Hypotheses' arrays), in place on pose,
    vel (N, 3): kinematic fingertips ``finger`` (F,) (indices into radius) moving
    linearly from c0 to c1 (F, 2) at v_f (F, 2) over the substeps, measured forces
    f_values (M, 2) N at f_points (M, 2).  Returns the fingers' forces (N, F, 2) N on
    the object, averaged over the substeps.  Scalar code, as forward3d's."""
    N, K, F, M = V.shape[0], V.shape[1], finger.shape[0], f_points.shape[0]
    eps2 = SLIP_REGULARIZATION ** 2
    ngx, ngy = n_g[0], n_g[1]
    tgx, tgy = n_g[1], -n_g[0]
    out = np.zeros((N, F, 2))
    for i in range(N):
        m, I = mass[i], inertia[i]
        k_g = m * g_mag / (2 * GROUND_SINK)
        c_g = 2 * DAMPING_RATIO * math.sqrt(k_g * m / 2)
        c_f = 2 * DAMPING_RATIO * math.sqrt(FINGER_STIFFNESS * m)
        for j in range(n_sub):
            a = (j + 1) / n_sub
            px, py, th = pose[i, 0], pose[i, 1], pose[i, 2]
            vx, vy, w = vel[i, 0], vel[i, 1], vel[i, 2]
            c, s = math.cos(th), math.sin(th)
            fx = fy = tq = 0.0
            for k in range(K):
                lx, ly = c * V[i, k, 0] - s * V[i, k, 1], s * V[i, k, 0] + c * V[i, k, 1]  # COM to vertex
                pen = h_ground - ((lx + px) * ngx + (ly + py) * ngy)
                if not pen > 0:  # NaN: no force, as off the ground
                    continue
                vvx, vvy = vx - w * ly, vy + w * lx
                vn = vvx * ngx + vvy * ngy
                vt = vvx * tgx + vvy * tgy
                fn = max(k_g * pen - c_g * vn, 0.0)
                ft = -mu_g[i] * fn * vt / math.sqrt(vt * vt + eps2)
                Fx, Fy = fn * ngx + ft * tgx, fn * ngy + ft * tgy
                fx, fy = fx + Fx, fy + Fy
                tq += lx * Fy - ly * Fx
            for f in range(F):
                cx, cy = (1 - a) * c0[f, 0] + a * c1[f, 0], (1 - a) * c0[f, 1] + a * c1[f, 1]
                sd, nx, ny, qx, qy = _closest(V[i], c, s, px, py, cx, cy)
                depth = radius[finger[f]] - sd
                if not depth > 0:  # NaN: no force, as out of reach
                    continue
                rx, ry = qx - px, qy - py
                # the fingertip's velocity relative to the surface point
                rel_x, rel_y = v_f[f, 0] - (vx - w * ry), v_f[f, 1] - (vy + w * rx)
                closing = -(rel_x * nx + rel_y * ny)  # > 0 while the finger moves into the object
                f_n = min(max(FINGER_STIFFNESS * depth + c_f * closing, 0.0), FINGER_FORCE_LIMIT)
                slip = rel_y * nx - rel_x * ny  # along the tangent (-ny, nx)
                f_t = mu_f[i] * f_n * slip / math.sqrt(slip * slip + eps2)
                Fx, Fy = -f_n * nx - f_t * ny, -f_n * ny + f_t * nx
                out[i, f, 0] += Fx / n_sub
                out[i, f, 1] += Fy / n_sub
                fx, fy = fx + Fx, fy + Fy
                tq += rx * Fy - ry * Fx
            for k in range(M):
                Fx, Fy = f_values[k, 0], f_values[k, 1]
                fx, fy = fx + Fx, fy + Fy
                tq += (f_points[k, 0] - px) * Fy - (f_points[k, 1] - py) * Fx
            vel[i, 0] = vx + h * (fx / m + g[0])
            vel[i, 1] = vy + h * (fy / m + g[1])
            vel[i, 2] = w + h * tq / I
            pose[i, 0] = px + h * vel[i, 0]
            pose[i, 1] = py + h * vel[i, 1]
            pose[i, 2] = th + h * vel[i, 2]
    return out


def rotations(angle) -> np.ndarray:
    """(N, 2, 2) rotation matrices (body to world) of angles (N,) rad."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def finger_geometry(hyp: Hypotheses, pose, centre__world):
    """Signed distance (N,) m of a point centre__world (2,) to each hypothesis' boundary
    (negative inside), the outward normal (N, 2) world at its closest boundary point,
    and that point (N, 2) world.  pose (N, 3) [x, y, angle]."""
    V = hyp.arrays()[0]
    pose = np.ascontiguousarray(pose, float)
    if pose.shape != (V.shape[0], 3):
        raise ValueError(f"finger_geometry: pose {pose.shape} for {V.shape[0]} hypotheses")
    c = np.asarray(centre__world, float).reshape(2)
    return _geometry(V, pose, float(c[0]), float(c[1]))


def kernel_drive(fingers, start_centres, forces, dim: int, who: str) -> tuple:
    """The fingertips and measured forces of one sample as the compiled kernels take them
    (2-D and 3-D, tacest.model.forward3d): ``fingers`` [(finger index, centre at the end
    (D,) m, velocity (D,) m/s)], ``start_centres`` [(D,) m] (empty: the end centres),
    ``forces`` [(point (D,) m, force (D,) N)] -> (finger indices (F,) int, start centres
    (F, D), end centres (F, D), velocities (F, D), force points (M, D), forces (M, D)).
    A ValueError names ``who`` when the start centres do not match the fingers."""
    F = len(fingers)
    if not len(start_centres):
        start_centres = [c for _, c, _ in fingers]
    if len(start_centres) != F:
        raise ValueError(f"{who}: {len(start_centres)} start centres for {F} fingers")
    idx = np.array([int(f) for f, _, _ in fingers], np.int64)
    c1 = np.array([np.asarray(c, float) for _, c, _ in fingers], float).reshape(F, dim)
    c0 = np.array([np.asarray(c, float) for c in start_centres], float).reshape(F, dim)
    v_f = np.array([np.asarray(v, float) for _, _, v in fingers], float).reshape(F, dim)
    f_points = np.array([np.asarray(p, float) for p, _ in forces], float).reshape(len(forces), dim)
    f_values = np.array([np.asarray(v, float) for _, v in forces], float).reshape(len(forces), dim)
    return idx, c0, c1, v_f, f_points, f_values


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

    def advance(self, hyp: Hypotheses, pose, vel, h, n_sub, fingers=(), start_centres=(), forces=()):
        """n_sub steps of h s (semi-implicit Euler) under gravity, the ground and the
        fingertips: ``fingers`` [(finger index, centre at the end (2,) m, velocity (2,)
        m/s)] kinematic spheres pushing by penetration, moving linearly from
        ``start_centres`` [(2,) m] (default: the end centres) to their end centres over
        the substeps (the k-th of n_sub at fraction k / n_sub); ``forces`` [(point (2,)
        m, force (2,) N)] applied to every hypothesis as measured, throughout.  Returns
        copies of the new (pose, vel) (N, 3) and the fingers' forces on the object
        (N, F, 2) N, averaged over the substeps, in the order of ``fingers``."""
        drive = kernel_drive(fingers, start_centres, forces, 2, "World2D.advance")
        arrays = hyp.arrays()
        n = arrays[0].shape[0]
        pose, vel = (np.array(a, float, order="C", copy=True) for a in (pose, vel))
        if pose.shape != (n, 3) or vel.shape != (n, 3):
            raise ValueError(f"World2D.advance: pose {pose.shape}, velocity {vel.shape} for {n} hypotheses")
        out = _advance(*arrays, pose, vel, self.n_g, self.h, self.g, self.g_mag, self.radius, *drive, int(n_sub),
                       float(h))
        return pose, vel, out

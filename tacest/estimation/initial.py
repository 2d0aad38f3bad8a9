"""Starting point of the NLP: a consistent object at rest on the ground, pushed along
quasi-statically by the measured contacts.

DESIGN's pitfall: a plain NLP started from a rough guess converges to nonsense (a box
twice too long floating in the air).  The start here is physically consistent: the
lowest face on the ground at t = 0, and at every later sample the object translated
just enough along the ground that no finger in contact is inside it (a frictionless,
rotation-free "push tracker").  The NLP then finds rotation, tipping, shape and
parameters from there.
"""

from __future__ import annotations

import numpy as np

from tacest.estimation.data import GRAVITY, Scales, touching
from tacest.geometry.shapes import numeric_vertices, polygon_sd_and_normal_function
from tacest.io.run import Run

#: |n·up| above which a measured normal counts as "from above" (a top-face touch): 45°
TOP_TOUCH_COS = 0.7


def contact_points(run: Run):
    """World-frame object surface points touched by the fingers, and their normals.

    Returns (idx_t (N,), idx_f (N,), p (N, 2) m, n (N, 2)) for every sample with
    contact (and not missing): p = finger centre - radius · measured normal.
    """
    if run.contact is None:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2))
    it, jf = np.nonzero(touching(run))
    n = run.normal[it, jf]
    p = run.finger_position[it, jf] - run.finger_radius[jf][:, None] * n
    return it, jf, p, n


def initial_extents(runs: list[Run], default_size: float):
    """Starting (width, height) in m: height from top touches when there are any."""
    heights = []
    for run in runs:
        _, _, p, n = contact_points(run)
        up = run.up
        top = n @ up > TOP_TOUCH_COS
        heights += list(p[top] @ up - run.ground_height)
    h = float(np.median(heights)) if heights else default_size
    h = float(np.clip(h, 0.2 * default_size, 5 * default_size))
    return default_size, h


def initial_pose(run: Run, width: float, height: float) -> np.ndarray:
    """Pose [x, y, angle] at t = 0: the run's prior if it has one, else resting on the
    ground with its side at the first side touch (or centred under the first top touch)."""
    if "initial_pose" in run.prior:
        return np.asarray(run.prior["initial_pose"], float)[:3].copy()
    if run.pose_obs is not None:
        ok = np.all(np.isfinite(run.pose_obs), axis=1)
        if ok.any():
            return run.pose_obs[np.argmax(ok)].copy()
    up = run.up
    horiz = np.array([up[1], -up[0]])
    base = run.ground_height * up
    it, jf, p, n = contact_points(run)
    if len(it) == 0:
        return np.array([*(base + 0.5 * height * up), 0.0])
    p0, n0 = p[0], n[0]
    along = p0 @ horiz
    if n0 @ up > TOP_TOUCH_COS:
        x = along
    else:
        side = np.sign(n0 @ horiz) or 1.0
        x = along - side * width / 2
    centre = base + 0.5 * height * up + x * horiz
    return np.array([centre[0], centre[1], 0.0])


def push_tracker(run: Run, V_body: np.ndarray, pose0: np.ndarray) -> np.ndarray:
    """(T, 3) poses: the object at rest at pose0, translated along the ground whenever a
    finger in contact would be inside it, just enough to clear it (no rotation)."""
    T = run.n_samples
    sd_fun = polygon_sd_and_normal_function(V_body.shape[0])
    poses = np.repeat(pose0[None, :], T, 0)
    if run.contact is None:
        return poses
    up = run.up
    horiz = np.array([up[1], -up[0]])
    cur = pose0.copy()
    for t in range(T):
        for f in range(run.n_fingers):
            if not run.contact[t, f] or not np.all(np.isfinite(run.normal[t, f])):
                continue
            c = run.finger_position[t, f]
            rad = run.finger_radius[f]
            R = np.array([[np.cos(cur[2]), -np.sin(cur[2])], [np.sin(cur[2]), np.cos(cur[2])]])
            sd = float(sd_fun((c - cur[:2]) @ R, V_body)[0])
            gap = sd - rad
            if gap < 0:
                n = run.normal[t, f]
                push = -(n @ horiz)
                if abs(push) > 0.2:  # mostly sideways: slide the object along the ground
                    cur[:2] += horiz * np.sign(push) * min(-gap / max(abs(push), 1e-6), 0.05)
        poses[t] = cur
    return poses


def finger_gaps(run: Run, V_body: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(T, F) gap between each fingertip sphere and the shape placed at poses (T, 3), m."""
    T, F = run.n_samples, run.n_fingers
    if not F:
        return np.zeros((T, 0))
    sd_fun = polygon_sd_and_normal_function(V_body.shape[0]).map(T * F)
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    rel = run.finger_position - poses[:, None, :2]  # (T, F, 2) world
    p_body = np.stack([c[:, None] * rel[..., 0] + s[:, None] * rel[..., 1],
                       -s[:, None] * rel[..., 0] + c[:, None] * rel[..., 1]], -1)
    sd = np.asarray(sd_fun(p_body.reshape(-1, 2).T, V_body)[0]).reshape(T, F)
    return sd - run.finger_radius[None, :]


#: candidate extents of the starting shape, as factors of the length scale L (geometric grid)
EXTENT_GRID = np.geomspace(0.4, 2.0, 11)


def touch_inconsistency(run: Run, V_body: np.ndarray, poses: np.ndarray) -> float:
    """m²: how badly a shape moved along poses (T, 3) disagrees with the contact flags:
    sum over samples of max(gap, 0)² where a finger touched and min(gap, 0)² where it
    did not."""
    if not run.n_fingers:
        return 0.0
    gaps = finger_gaps(run, V_body, poses)
    on = touching(run)
    off = ~run.contact.astype(bool)
    if run.missing is not None:
        off &= ~run.missing.astype(bool)[:, None]
    return float(np.sum(np.maximum(gaps[on], 0) ** 2) + np.sum(np.minimum(gaps[off], 0) ** 2))


def choose_start_shape(problem, runs: list[Run], scales: Scales, s_guess: np.ndarray) -> np.ndarray:
    """Starting shape parameters: among shapes of width × height on :data:`EXTENT_GRID`
    (and the given guess), the one whose push-tracker trajectories agree best with the
    contact flags (:func:`touch_inconsistency`).  Touches from both sides of a resting
    object fix its width; top touches its height."""
    if not any(r.n_fingers for r in runs):
        return np.asarray(s_guess, float)
    L = scales.L
    best, best_cost = np.asarray(s_guess, float), np.inf
    candidates = [np.asarray(s_guess, float)] + [problem.shape.initial(w, h) for w in EXTENT_GRID
                                                   for h in EXTENT_GRID]
    for s in candidates:
        V = numeric_vertices(problem.shape, s, L)
        cost = sum(touch_inconsistency(run, V, _tracked(run, V)) for run in runs)
        if cost < best_cost - 1e-12:
            best, best_cost = s, cost
    return best


def start_trajectories(problem, runs: list[Run], scales: Scales, s0: np.ndarray):
    """(T, 3) push-tracker pose trajectories of the starting shape, one per run."""
    V = numeric_vertices(problem.shape, s0, scales.L)
    return [_tracked(run, V) for run in runs]


def _tracked(run: Run, V: np.ndarray) -> np.ndarray:
    w = V[:, 0].max() - V[:, 0].min()
    h = V[:, 1].max() - V[:, 1].min()
    pose0 = initial_pose(run, w, h)
    # put the lowest vertex exactly on the ground at the start
    R0 = np.array([[np.cos(pose0[2]), -np.sin(pose0[2])], [np.sin(pose0[2]), np.cos(pose0[2])]])
    lowest = np.min((V @ R0.T + pose0[:2]) @ run.up) - run.ground_height
    pose0[:2] -= lowest * run.up
    return push_tracker(run, V, pose0)


def initial_guess(problem, runs: list[Run], scales: Scales, s0: np.ndarray, trajectories=None):
    """Scaled decision vector z0 for :class:`Problem2D`: theta (shape s0, log mass 0,
    log inertia ratio 0, friction 0.5, 0.5) and, per run, the given (or push-tracker)
    trajectory, finite-difference velocities, and impulses that hold the object up."""
    z0 = np.zeros(problem.n_z)
    ns = problem.n_shape
    z0[:ns] = s0
    z0[ns:ns + 4] = [0.0, 0.0, 0.5, 0.5]
    z0[problem.phys_offset: problem.phys_offset + problem.n_phys] = np.asarray(
        problem.phys_sx(z0[: problem.n_theta], scales.L, scales.m0)).reshape(-1)
    V = numeric_vertices(problem.shape, s0, scales.L)
    K = problem.K
    for i, run in enumerate(runs):
        poses = trajectories[i] if trajectories is not None else _tracked(run, V)
        T = run.n_samples
        vel = np.zeros_like(poses)
        vel[1:] = np.diff(poses, axis=0) / run.dt
        scale = np.array([scales.L, scales.L, 1.0])
        Q = (poses / scale).T
        Vv = (vel / scale).T
        LG = np.zeros((2 * K, T - 1))  # [normal; tangential], tangential 0 (sticking)
        # ground: weight carried by the vertices within 1 mm of the ground
        for t in range(1, T):
            Rt = np.array([[np.cos(poses[t, 2]), -np.sin(poses[t, 2])], [np.sin(poses[t, 2]), np.cos(poses[t, 2])]])
            phi = (V @ Rt.T + poses[t, :2]) @ run.up - run.ground_height
            low = phi < phi.min() + 1e-3
            LG[:K, t - 1][low] = 1.0 / low.sum()
        LF = np.zeros((2 * run.n_fingers, T - 1))
        if run.n_fingers:
            Lam = scales.m0 * GRAVITY * run.dt
            on = run.contact[1:].astype(bool)
            n = np.where(np.isfinite(run.normal[1:]), run.normal[1:], 0.0)
            imp = run.force[1:] * run.dt / Lam if run.force is not None else -0.3 * n
            LF = (imp * on[:, :, None]).reshape(T - 1, -1).T
        problem.set_run_blocks(z0, i, Q=Q, V=Vv, LG=LG, LF=LF)
    return z0

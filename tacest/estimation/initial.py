"""Starting point of the NLP: a consistent object at rest on the ground, pushed along
quasi-statically by the measured contacts, or the observed poses where there are any.

DESIGN's pitfall: a plain NLP started from a rough guess converges to nonsense (a box
twice too long floating in the air).  The start here is physically consistent: the
lowest face on the ground at t = 0, and at every later sample the object translated
just enough along the ground that no finger in contact is inside it (a frictionless,
rotation-free "push tracker").  The NLP then finds rotation, tipping, shape and
parameters from there.  A run with pose observations (``/observations/pose``) starts
on its observed trajectory instead (missing rows interpolated), which already holds
the tipping and turning the push tracker cannot know of.
"""

from __future__ import annotations

import numpy as np

from tacest.estimation.data import Scales, pose_observation_columns, starts_at_rest, touch_inconsistency, touching
from tacest.geometry.polygon import convex_signed_distance
from tacest.geometry.shapes import numeric_vertices
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
    ground with its side at the first side touch (or centred under the first top touch:
    the middle of :func:`initial_pose_range`)."""
    return initial_pose_range(run, width, height)[0]


def initial_pose_range(run: Run, width: float, height: float) -> tuple:
    """(pose (3,) [x, y, angle] at t = 0, half range m): where the object rests before it
    is first touched and how far along the ground its centre may lie either side of that
    pose.  The run's prior or its first observed pose: range 0.  Else it rests on the
    ground: a first touch on a side face puts that face at the touch (range 0); one on
    the top face only says that the top face is under it, anywhere along its width
    (the centre within ``width`` / 2 either side of the touch: a fingertip that lands
    on the top face near a corner is as likely as one at the middle); no touch, at the
    origin along the ground."""
    if "initial_pose" in run.prior:
        return np.asarray(run.prior["initial_pose"], float)[:3].copy(), 0.0
    if run.pose_obs is not None:
        ok = np.all(np.isfinite(run.pose_obs), axis=1)
        if ok.any():
            return run.pose_obs[np.argmax(ok)].copy(), 0.0
    up = run.up
    horiz = np.array([up[1], -up[0]])
    base = run.ground_height * up
    it, jf, p, n = contact_points(run)
    if len(it) == 0:
        return np.array([*(base + 0.5 * height * up), 0.0]), 0.0
    p0, n0 = p[0], n[0]
    along = p0 @ horiz
    if n0 @ up > TOP_TOUCH_COS:
        x, half_range = along, 0.5 * width
    else:
        side = np.sign(n0 @ horiz) or 1.0
        x, half_range = along - side * width / 2, 0.0
    centre = base + 0.5 * height * up + x * horiz
    return np.array([centre[0], centre[1], 0.0]), half_range


#: fewest observed pose rows for a run to start on its observed trajectory
MIN_OBSERVED_ROWS = 2


#: window (s) of the local quadratic that smooths observed poses for the start: the
#: velocities of the start are differences of its poses, and at 100 Hz a raw 0.5 mm
#: position noise gives velocity changes of ~20 process sigmas per sample, which the
#: solver first removes by making the object light (the dynamics residual scales with
#: the mass) and then stays in that basin; 0.07 s keeps a tipping fall's shape
OBSERVED_SMOOTHING_S = 0.07


def observed_trajectory(run: Run):
    """(T, 3) poses [x, y, angle] (m, m, rad) of the run's pose observations, the angle
    unwrapped, rows that were not observed interpolated linearly (held constant before
    the first and after the last observed row), then smoothed by a local quadratic over
    :data:`OBSERVED_SMOOTHING_S`; None without observations or with fewer than
    :data:`MIN_OBSERVED_ROWS` observed rows."""
    obs, observed = pose_observation_columns(run)  # angle unwrapped over the observed rows
    t_obs = np.nonzero(observed[:, 0])[0]
    if len(t_obs) < MIN_OBSERVED_ROWS:
        return None
    t_all = np.arange(run.n_samples)
    poses = np.stack([np.interp(t_all, t_obs, obs[t_obs, j]) for j in range(3)], axis=1)
    return smooth_quadratic(poses, run.dt, OBSERVED_SMOOTHING_S)


def smooth_polynomial(x, window: int, order: int) -> np.ndarray:
    """x (T, n) smoothed by a local polynomial of ``order`` over ``window`` samples (odd,
    order + 2 <= window <= T): a least-squares polynomial through each window's samples,
    evaluated at its centre (Savitzky–Golay), and within half a window of either end the
    polynomial of the first or last whole window evaluated there."""
    x = np.asarray(x, float)
    T = x.shape[0]
    h = window // 2
    u = np.arange(-h, h + 1, dtype=float)
    A = np.vander(u, order + 1, increasing=True)  # columns 1, u, u², ...
    fit = np.linalg.pinv(A)  # (order + 1, window): coefficients of the least-squares polynomial
    out = x.copy()
    # interior: the fitted value at the centre, i.e. a correlation with fit[0]
    windows = np.lib.stride_tricks.sliding_window_view(x, window, axis=0)  # (T - 2h, n, window)
    out[h: T - h] = windows @ fit[0]
    # ends: the first and last windows' polynomials evaluated at their outer samples
    for start, edge in ((0, np.arange(h)), (T - window, np.arange(T - h, T))):
        coef = fit @ x[start: start + window]  # (order + 1, n)
        out[edge] = np.vander(edge - (start + h), order + 1, increasing=True).astype(float) @ coef
    return out


def smooth_quadratic(x, dt: float, window_s: float) -> np.ndarray:
    """x (T, n) smoothed by a local quadratic over window_s seconds (the odd number of
    samples nearest window_s / dt; :func:`smooth_polynomial` of order 2); x unchanged when
    the window would be under 5 samples or longer than x."""
    x = np.asarray(x, float)
    window = 2 * int(round(window_s / dt / 2)) + 1
    if window < 5 or x.shape[0] < window:
        return x.copy()
    return smooth_polynomial(x, window, 2)


def _rotations(angles):
    """(..., 2, 2) rotation matrices of angles (...,) rad."""
    c, s = np.cos(angles), np.sin(angles)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def push_tracker_batch(run: Run, V_bodies: np.ndarray, poses0: np.ndarray, t0: int = 0) -> np.ndarray:
    """(N, T, 3) poses of N shapes V_bodies (N, K, 2) m, each at rest at its pose0 (N, 3)
    and, from sample t0 on, translated along the ground whenever a finger in contact
    would be inside it, just enough to clear it (no rotation); vectorized over the
    shapes, sequential in time."""
    T = run.n_samples
    poses = np.repeat(poses0[:, None, :], T, 1)
    if run.contact is None:
        return poses
    up = run.up
    horiz = np.array([up[1], -up[0]])
    cur = poses0.astype(float).copy()
    R = _rotations(cur[:, 2])  # the tracker never rotates
    on = run.contact.astype(bool) & np.all(np.isfinite(run.normal), axis=-1)
    for t in range(t0, T):
        for f in np.nonzero(on[t])[0]:
            c = run.finger_position[t, f]
            push = -(run.normal[t, f] @ horiz)
            if abs(push) <= 0.2:  # mostly from above: the tracker does not slide the object
                continue
            p_body = np.einsum("nji,nj->ni", R, c[None] - cur[:, :2])
            gap = convex_signed_distance(p_body, V_bodies) - run.finger_radius[f]
            step = np.where(gap < 0, np.minimum(-gap / max(abs(push), 1e-6), 0.05), 0.0)
            cur[:, :2] += step[:, None] * np.sign(push) * horiz[None]
        poses[:, t] = cur
    return poses


def continued_trajectory(run: Run, V_body: np.ndarray, poses_before: np.ndarray) -> np.ndarray:
    """(T, 3) poses [x, y m, angle rad] of the shape V_body (K, 2) m that follow
    ``poses_before`` (T0, 3) (T0 <= T: e.g. an earlier estimate's trajectory of the
    first T0 samples of ``run``) and, from there, the push tracker's motion
    (:func:`push_tracker_batch`) from the last of those poses."""
    poses_before = np.asarray(poses_before, float)
    T0 = len(poses_before)
    if not 0 < T0 <= run.n_samples or poses_before.shape[1:] != (3,):
        raise ValueError(f"poses_before must be (T0, 3) with 0 < T0 <= {run.n_samples}, got {poses_before.shape}")
    out = push_tracker_batch(run, np.asarray(V_body, float)[None], poses_before[-1][None], t0=T0)[0]
    out[:T0] = poses_before
    return out


def finger_gaps(run: Run, V_body: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(T, F) gap between each fingertip sphere and the shape placed at poses (T, 3), m."""
    return finger_gaps_batch(run, V_body[None], poses[None])[0]


def finger_gaps_batch(run: Run, V_bodies: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """:func:`finger_gaps` for N shapes (N, K, 2) along their poses (N, T, 3) -> (N, T, F)."""
    T, F = run.n_samples, run.n_fingers
    N = V_bodies.shape[0]
    if not F:
        return np.zeros((N, T, 0))
    R = _rotations(poses[..., 2])  # (N, T, 2, 2)
    rel = run.finger_position[None, :, :, :] - poses[:, :, None, :2]  # (N, T, F, 2) world
    p_body = np.einsum("ntji,ntfj->ntfi", R, rel)
    sd = convex_signed_distance(p_body, V_bodies[:, None, None])
    return sd - run.finger_radius[None, None, :]


#: candidate extents of the starting shape, as factors of the length scale L (geometric grid)
EXTENT_GRID = np.geomspace(0.4, 2.0, 11)
#: two starting shapes are distinct when one's width or height is more than this factor
#: of the other's (about 1.4 grid steps of EXTENT_GRID)
DISTINCT_EXTENT_RATIO = 1.25


def touch_inconsistency_batch(run: Run, V_bodies: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(N,) m²: how badly each of N shapes (N, K, 2) moved along its poses (N, T, 3)
    disagrees with the contact flags: the sum over samples of max(gap, 0)² where a finger
    touched and min(gap, 0)² where it did not (data.touch_inconsistency)."""
    if not run.n_fingers:
        return np.zeros(V_bodies.shape[0])
    return touch_inconsistency(run, finger_gaps_batch(run, V_bodies, poses))


#: cap (as a factor of the length scale L) on how far a shape placed on observed poses
#: may float above the ground in :func:`ground_inconsistency_batch`: floating while the
#: object flies or falls costs every candidate about the same, so it cannot outweigh
#: the penetration of a shape that is too large
FLOAT_CAP_L = 0.5


def ground_inconsistency_batch(run: Run, V_bodies: np.ndarray, poses: np.ndarray, L: float) -> np.ndarray:
    """(N,) m²: how badly each of N shapes (N, K, 2) placed on its poses (N, T, 3)
    disagrees with a ground it rests on: the sum over the observed samples (all samples
    without observations) of min(φ, 0)² + min(max(φ, 0), FLOAT_CAP_L·L)², φ the height
    of the lowest vertex above the ground.  Zero for push-tracked poses (they keep the
    lowest vertex on the ground); for observed poses it measures the extents that the
    resting and tipping object shows."""
    R = _rotations(poses[..., 2])  # (N, T, 2, 2)
    world = np.einsum("ntij,nkj->ntki", R, V_bodies) + poses[:, :, None, :2]
    phi = np.min(world @ run.up, axis=2) - run.ground_height  # (N, T)
    cost = np.minimum(phi, 0.0) ** 2 + np.minimum(np.maximum(phi, 0.0), FLOAT_CAP_L * L) ** 2
    if run.pose_obs is not None:
        cost = cost * np.all(np.isfinite(run.pose_obs), axis=1)[None]
    return np.sum(cost, axis=1)


def start_shape_candidates(problem, runs: list[Run], scales: Scales, s_guess: np.ndarray,
                           n: int = 1) -> list:
    """Up to n distinct starting shapes (shape parameter vectors), best first: among
    shapes of width × height on :data:`EXTENT_GRID` (and the given guess), ordered by how
    well their starting trajectories (push-tracked, or observed) agree with the contact
    flags (:func:`touch_inconsistency_batch`; touches from both sides of a resting
    object fix its width, top touches its height) and with the ground
    (:func:`ground_inconsistency_batch`; observed poses of a resting or tipping object
    fix its extents).  Each later shape differs from every earlier one
    by more than :data:`DISTINCT_EXTENT_RATIO` in width or height, so that a restart from
    it explores another basin, not a neighbour of a failed start."""
    if not any(r.n_fingers or observed_trajectory(r) is not None for r in runs):
        return [np.asarray(s_guess, float)]
    L = scales.L
    candidates = [np.asarray(s_guess, float)] + [problem.shape.initial(w, h) for w in EXTENT_GRID
     for h in EXTENT_GRID]
    Vs = np.stack([numeric_vertices(problem.shape, s, L) for s in candidates])
    cost = 0.0
    for run in runs:
        poses = _tracked_batch(run, Vs)
        cost = cost + touch_inconsistency_batch(run, Vs, poses) + ground_inconsistency_batch(run, Vs, poses, L)
    # the cheapest first (the guess wins ties: stable sort, guess at index 0)
    order = np.argsort(cost, kind="stable")
    extents = np.ptp(Vs, axis=1)  # (N, 2) m
    picked = []
    for k in order:
        ratio = np.abs(np.log(extents[k][None] / extents[picked]))
        if not picked or np.all(np.max(ratio, axis=1) > np.log(DISTINCT_EXTENT_RATIO)):
            picked.append(int(k))
        if len(picked) == n:
            break
    return [candidates[k] for k in picked]


def choose_start_shape(problem, runs: list[Run], scales: Scales, s_guess: np.ndarray) -> np.ndarray:
    """The best starting shape of :func:`start_shape_candidates`."""
    return start_shape_candidates(problem, runs, scales, s_guess, 1)[0]


def start_trajectories(problem, runs: list[Run], scales: Scales, s0: np.ndarray):
    """(T, 3) starting pose trajectories of the shape s0, one per run: the observed
    trajectory where the run has one, else the push tracker's."""
    V = numeric_vertices(problem.shape, s0, scales.L)
    return [_tracked(run, V) for run in runs]


def _tracked(run: Run, V: np.ndarray) -> np.ndarray:
    return _tracked_batch(run, V[None])[0]


def _tracked_batch(run: Run, Vs: np.ndarray) -> np.ndarray:
    """(N, T, 3) starting trajectories of N shapes (N, K, 2): the observed trajectory
    (:func:`observed_trajectory`) for every shape where the run has one, else push-tracker
    trajectories, each starting at its :func:`initial_pose` with its lowest vertex
    exactly on the ground."""
    observed = observed_trajectory(run)
    if observed is not None:
        return np.repeat(observed[None], Vs.shape[0], axis=0)
    poses0 = []
    for V in Vs:
        w = V[:, 0].max() - V[:, 0].min()
        h = V[:, 1].max() - V[:, 1].min()
        pose0 = initial_pose(run, w, h)
        R0 = _rotations(pose0[2])
        lowest = np.min((V @ R0.T + pose0[:2]) @ run.up) - run.ground_height
        pose0[:2] -= lowest * run.up
        poses0.append(pose0)
    return push_tracker_batch(run, Vs, np.array(poses0))


def initial_guess(problem, runs: list[Run], scales: Scales, s0: np.ndarray, trajectories=None):
    """Scaled decision vector z0 for :class:`Problem2D`: theta (shape s0, log mass 0,
    log inertia ratio 0, friction 0.5, 0.5, effect parameters at their starts: "no
    effect" unless the parameter says otherwise, tacest.model.effect.EffectParameter)
    and, per run, the given (or push-tracker)
    trajectory, finite-difference velocities, and impulses that hold the object up."""
    z0 = np.zeros(problem.n_z)
    ns = problem.n_shape
    z0[:ns] = s0
    z0[ns:ns + 4] = [0.0, 0.0, 0.5, 0.5]
    for j, (_, par) in enumerate(problem.effect_params):
        z0[ns + 4 + j] = par.centre if par.start is None else par.start
    z0[problem.phys_offset: problem.phys_offset + problem.n_phys] = np.asarray(
        problem.phys_sx(z0[: problem.n_theta], scales.L, scales.m0)).reshape(-1)
    V = numeric_vertices(problem.shape, s0, scales.L)
    K = problem.K
    for i, run in enumerate(runs):
        poses = trajectories[i] if trajectories is not None else _tracked(run, V)
        T = run.n_samples
        vel = np.zeros_like(poses)
        vel[1:] = np.diff(poses, axis=0) / run.dt
        if not starts_at_rest(run) and T > 1:  # a free start moves as its next sample does
            vel[0] = vel[1]
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
            Lam = scales.m0 * scales.g * run.dt
            on = run.contact[1:].astype(bool)
            n = np.where(np.isfinite(run.normal[1:]), run.normal[1:], 0.0)
            imp = run.force[1:] * run.dt / Lam if run.force is not None else -0.3 * n
            LF = (imp * on[:, :, None]).reshape(T - 1, -1).T
        problem.set_run_blocks(z0, i, Q=Q, V=Vv, LG=LG, LF=LF)
    return z0

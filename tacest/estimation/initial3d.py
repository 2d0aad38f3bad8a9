"""Starting points of the 3-D estimator for runs without pose observations.

Without pose observations the plain start is the object resting at its initial pose for
the whole run, however far the fingers pushed it; the NLP must then find the pushes
itself, and from a start far from them it often stops at its iteration limit or in a
local minimum (a shape floating or sinking to follow the touches).  As in 2-D
(initial.py) the remedy is a physically plausible start that follows the touches, for a
few candidate extents:

* the **push tracker**: the object rests on the ground at its initial pose; at every
  sample where a fingertip in contact would be inside it, it slides along the ground
  (along the horizontal part of the measured push) just enough to clear the fingertip;
  its yaw about the up axis follows the measured normals of side touches (a side face's
  outward normal turns with the object; the face is the one whose normal is nearest;
  touches at edges and corners are left out);
  it never tips;
* the **candidates**: box extents (w, d, h) on a geometric grid, ranked by how well
  their tracked trajectories agree with the contact flags
  (:func:`touch_inconsistency_3d`: a touching fingertip should be on the surface, a
  non-touching one outside), each picked box refined on a finer grid around it, plus
  the plain resting start; distinct candidates differ by more than
  :data:`DISTINCT_EXTENT_RATIO` in some extent.

Shapes other than boxes use the box of the same extents for the tracker (their starting
shape is inscribed in it, :meth:`Shape3D.initial`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tacest.estimation.data import touch_inconsistency, touching
# the grid of candidate extents (factors of L) and the distinctness of starts, as in 2-D
from tacest.estimation.initial import DISTINCT_EXTENT_RATIO, EXTENT_GRID, smooth_polynomial
from tacest.geometry.transforms import quat_to_matrix
from tacest.io.run import Run

#: |n·up| below which a measured normal counts as a side touch (its horizontal part sets
#: the push direction and the yaw): 45°, as initial.TOP_TOUCH_COS in 2-D
SIDE_TOUCH_COS = 0.7
#: largest slide per sample (m): 5 cm, as in 2-D (a fingertip far inside a wrong shape
#: is cleared over a few samples instead of throwing the object across the scene)
MAX_STEP = 0.05
#: side-touch samples whose yaw estimates are combined by a median (about 0.1 s at
#: 100 Hz): a single normal at an edge or corner can be off by 10-15°
YAW_MEDIAN_WINDOW = 9
#: side-touch samples of one contact before its normals turn the object (0.05 s at
#: 100 Hz): the first normals of a contact, at an edge or corner, can be off by 10-20°
YAW_MIN_SAMPLES = 5
#: |n·up| below which a side touch's normal sets the yaw (within 17° of horizontal): at
#: a top edge or corner (|n·up| 0.3-0.7) its horizontal part is 10° and more off the face
YAW_TOUCH_COS = 0.3
#: largest difference (rad) between a side touch's face yaw and the current yaw for the
#: touch to turn the object (6°): at a vertical edge the measured normal bisects two
#: faces and points 20-45° off both; pushes turn a box by a few degrees per poke,
#: gradually, and the median window follows such a turn within a contact
YAW_ACCEPT = np.radians(6.0)
#: s: width of the centred moving average smoothing the tracked yaw (0.3 s, 31 samples
#: at 100 Hz).  The median track turns in steps of a few tenths of a degree per sample
#: (normal noise ~2°), an angular velocity of ~0.5 rad/s noise that the rotational
#: dynamics cannot explain; IPOPT then ends at its iteration limit or in a poor local
#: minimum (seed 5 of the simulated pokes, true extents: unsmoothed, the iteration
#: limit; smoothed over 0.3 s, objective 105, 107 at the truth)
YAW_SMOOTH_TIME = 0.3
#: factors around a picked grid box tried by the refinement (4.4 % steps over one step
#: of EXTENT_GRID either way): a box 7 mm too large on a 12 cm object, within one coarse
#: step, holds the tracked object several mm off the touches, and the fit from it ends
#: in a poor local minimum (seed 5: objective 931 vs 105 from the true extents)
EXTENT_REFINE = np.geomspace(1 / 1.19, 1.19, 9)
#: relative cost preference per squared log-extent (units of L) breaking ties between
#: candidate boxes (start_candidates_3d)
TIE_PREFERENCE = 0.02


#: Savitzky–Golay window (samples, odd) and polynomial order of the starting trajectory
#: of pose-observed runs (:func:`smoothed_start_track`)
START_SMOOTH_WINDOW = 11
START_SMOOTH_ORDER = 3


def smoothed_start_track(poses: np.ndarray, window: int = START_SMOOTH_WINDOW) -> np.ndarray:
    """(T, 7) starting poses from observed ones (T, 7) (m, unit quaternions with
    continuous signs): a cubic Savitzky–Golay smoothing over START_SMOOTH_WINDOW samples,
    quaternions renormalised (``window`` samples, odd).  Only the start: the pose
    residuals use the observations.

    Why: the dynamics residuals of the start are second differences of the poses, so an
    observation noise sigma becomes accelerations of ~sigma / dt² (0.5 mm at 100 Hz:
    5 m/s², 10 mrad: 100 rad/s²).  From the raw observations the first Gauss–Newton
    steps absorb that noise into the slowest parameters: on simulated topples (MuJoCo,
    noiseless finger sensors, poses at 0.5 mm) the inertia grew up to 70x and the mass
    up to 64 % off, objective 1000–2100; from the smoothed start the same fits end at
    810–1180 with the mass within 0.4–5 % (docs/estimation3d.md, "Pose-observed
    starts"); the sampler's lineages are smoothed the same way over 0.07 s (smc3d)."""
    T = poses.shape[0]
    window = min(int(window), T if T % 2 else T - 1)
    if window <= START_SMOOTH_ORDER + 1:
        return poses
    out = smooth_polynomial(poses, window, START_SMOOTH_ORDER)
    out[:, 3:] /= np.linalg.norm(out[:, 3:], axis=1, keepdims=True)
    return out


@dataclass
class Start3D:
    """One starting point: box extents (3,) in units of L, and per run the (T, 7) poses
    [x, y, z m, qw, qx, qy, qz], or None for the plain resting start."""

    extents: np.ndarray
    poses: list | None
    label: str
    inconsistency: float
    #: the shape parameters (scaled) to start from where they are not the box of
    #: ``extents`` (an earlier estimate's shape), else None
    shape_params: np.ndarray | None = None
    #: what the start's attempt record carries besides (the sampler's seed, likelihood, tilt)
    extra: dict = field(default_factory=dict)


def _frame(up: np.ndarray, R0: np.ndarray):
    """Horizontal unit vectors (h1, h2) with (h1, h2, up) right-handed; h1 along the
    body x axis of orientation R0 projected on the ground plane."""
    up = up / np.linalg.norm(up)
    h1 = R0[:, 0] - (R0[:, 0] @ up) * up
    if np.linalg.norm(h1) < 1e-6:
        h1 = R0[:, 1] - (R0[:, 1] @ up) * up
    h1 /= np.linalg.norm(h1)
    return h1, np.cross(up, h1)


def _axis_rotation(up: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations by yaw (...) rad about the unit axis up (Rodrigues)."""
    K = np.array([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]])
    s, c = np.sin(yaw)[..., None, None], np.cos(yaw)[..., None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions [w, x, y, z] of rotations (..., 3, 3) (w >= 0)."""
    R = np.asarray(R, float)
    w = np.sqrt(np.maximum(1 + R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2], 0)) / 2
    x = np.sqrt(np.maximum(1 + R[..., 0, 0] - R[..., 1, 1] - R[..., 2, 2], 0)) / 2
    y = np.sqrt(np.maximum(1 - R[..., 0, 0] + R[..., 1, 1] - R[..., 2, 2], 0)) / 2
    z = np.sqrt(np.maximum(1 - R[..., 0, 0] - R[..., 1, 1] + R[..., 2, 2], 0)) / 2
    x = np.copysign(x, R[..., 2, 1] - R[..., 1, 2])
    y = np.copysign(y, R[..., 0, 2] - R[..., 2, 0])
    z = np.copysign(z, R[..., 1, 0] - R[..., 0, 1])
    q = np.stack([w, x, y, z], -1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def initial_orientation(run: Run) -> np.ndarray:
    """(3, 3) the orientation at t = 0: the prior's initial pose, else unrotated."""
    if "initial_pose" in run.prior:
        q = np.asarray(run.prior["initial_pose"], float)[3:7]
        return quat_to_matrix(q / np.linalg.norm(q))
    return np.eye(3)


def initial_position(run: Run, extents_m: np.ndarray, R0: np.ndarray) -> np.ndarray:
    """(N, 3) m: the prior's initial position, else at the origin; for every box of
    extents (N, 3) m moved along up so that its lowest corner is on the ground."""
    pos = np.zeros(3)
    if "initial_pose" in run.prior:
        pos = np.asarray(run.prior["initial_pose"], float)[:3].copy()
    up = np.asarray(run.up, float)
    reach = 0.5 * extents_m @ np.abs(R0.T @ up)  # (N,) support distance downward
    height = pos @ up - run.ground_height
    return pos[None] + (reach - height)[:, None] * up[None]


def yaw_track(run: Run) -> np.ndarray:
    """(T,) rad: the yaw about up of the tracked object relative to its initial
    orientation.  At side touches the outward face normal is the measured normal, so
    the yaw is the angle of the normal's horizontal part less a multiple of 90° (the
    face nearest the current yaw), combined over the last :data:`YAW_MEDIAN_WINDOW`
    side-touch samples of the same contact by a median once there are
    :data:`YAW_MIN_SAMPLES`; elsewhere it holds.  The result is smoothed by a centred
    moving average of :data:`YAW_SMOOTH_TIME`."""
    T = run.n_samples
    yaw = np.zeros(T)
    if not run.n_fingers:
        return yaw
    up = np.asarray(run.up, float)
    up = up / np.linalg.norm(up)
    h1, h2 = _frame(up, initial_orientation(run))
    on = touching(run) & np.all(np.isfinite(run.normal), axis=-1)
    cur = 0.0
    recent: dict[int, list] = {}
    for t in range(T):
        for f in range(run.n_fingers):
            if not on[t, f]:
                recent.pop(f, None)
                continue
            n = run.normal[t, f]
            if abs(n @ up) >= YAW_TOUCH_COS:
                continue
            a = float(np.arctan2(n @ h2, n @ h1))
            psi = a - np.round((a - cur) / (np.pi / 2)) * (np.pi / 2)  # the face nearest the current yaw
            if abs(psi - cur) > YAW_ACCEPT:
                continue  # an edge or corner touch
            buf = recent.setdefault(f, [])
            buf.append(psi)
            del buf[:-YAW_MEDIAN_WINDOW]
            if len(buf) >= YAW_MIN_SAMPLES:
                cur = float(np.median(buf))
        yaw[t] = cur
    width = int(round(YAW_SMOOTH_TIME / run.dt)) | 1  # odd: centred
    if width > 1 and T > 1:
        pad = np.concatenate([np.full(width // 2, yaw[0]), yaw, np.full(width // 2, yaw[-1])])
        yaw = np.convolve(pad, np.ones(width) / width, mode="valid")
    return yaw


def _box_signed_distance(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Signed distance (m) of body-frame points p (..., 3) to boxes of half extents
    half (..., 3) m (negative inside).  Written per component: the start search
    evaluates it on (boxes, samples, fingers) arrays of millions of points."""
    q = np.abs(p) - half
    qx, qy, qz = q[..., 0], q[..., 1], q[..., 2]
    ox, oy, oz = np.maximum(qx, 0), np.maximum(qy, 0), np.maximum(qz, 0)
    return np.sqrt(ox * ox + oy * oy + oz * oz) + np.minimum(np.maximum(np.maximum(qx, qy), qz), 0)


def push_tracker_3d(run: Run, extents_m: np.ndarray) -> np.ndarray:
    """(N, T, 7) poses of N boxes of extents (N, 3) m, each at rest at its initial pose
    (:func:`initial_position`), turned by :func:`yaw_track` and slid along the ground
    whenever a touching fingertip would be inside it, just enough to clear it;
    vectorized over the boxes, sequential in time."""
    extents_m = np.atleast_2d(np.asarray(extents_m, float))
    up = np.asarray(run.up, float)
    up = up / np.linalg.norm(up)
    R0 = initial_orientation(run)
    Rt = _axis_rotation(up, yaw_track(run)) @ R0  # (T, 3, 3), shared by all boxes
    pos = _slide_clear(run, 0.5 * extents_m, initial_position(run, extents_m, R0), Rt, 0)
    q = np.repeat(_quat_from_matrix(Rt)[None], len(extents_m), 0)
    return np.concatenate([pos, q], -1)


def continued_track(run: Run, extents_m: np.ndarray, poses_before: np.ndarray) -> np.ndarray:
    """(T, 7) poses of a box of extents (3,) m that follow ``poses_before`` (T0, 7)
    [x, y, z m, qw, qx, qy, qz] (T0 <= T: e.g. an earlier estimate's trajectory of the
    first T0 samples of ``run``) and, from there, the push tracker's motion
    (:func:`push_tracker_3d`) from the last of those poses: turned by the change of
    :func:`yaw_track` since sample T0 - 1, slid clear of touching fingertips."""
    poses_before = np.asarray(poses_before, float)
    T, T0 = run.n_samples, len(poses_before)
    if not 0 < T0 <= T or poses_before.shape[1:] != (7,):
        raise ValueError(f"poses_before must be (T0, 7) with 0 < T0 <= {T}, got {poses_before.shape}")
    up = np.asarray(run.up, float)
    up = up / np.linalg.norm(up)
    q_last = poses_before[-1, 3:] / np.linalg.norm(poses_before[-1, 3:])
    yaw = yaw_track(run)
    Rt = _axis_rotation(up, yaw - yaw[T0 - 1]) @ quat_to_matrix(q_last)
    half = 0.5 * np.asarray(extents_m, float).reshape(1, 3)
    pos = _slide_clear(run, half, poses_before[-1:, :3], Rt, T0)[0]
    out = np.concatenate([pos, _quat_from_matrix(Rt)], -1)
    out[:T0] = poses_before
    return out


def _slide_clear(run: Run, half: np.ndarray, start: np.ndarray, Rt: np.ndarray, t0: int) -> np.ndarray:
    """(N, T, 3) m: the positions of N boxes of half extents ``half`` (N, 3) m and
    orientations Rt (T, 3, 3), at ``start`` (N, 3) until sample t0 and from there slid
    along the ground whenever a touching fingertip would be inside one (push tracker)."""
    T = run.n_samples
    up = np.asarray(run.up, float)
    up = up / np.linalg.norm(up)
    cur = np.array(start, float)
    pos = np.repeat(cur[:, None], T, 1)
    on = (touching(run) & np.all(np.isfinite(run.normal), axis=-1)) if run.n_fingers else np.zeros((T, 0), bool)
    for t in range(t0, T):
        for f in np.nonzero(on[t])[0]:
            n = run.normal[t, f]
            push = -(n - (n @ up) * up)  # horizontal part of the push on the object
            size = np.linalg.norm(push)
            if abs(n @ up) >= SIDE_TOUCH_COS or size < 1e-9:
                continue  # mostly from above: the tracker does not slide the object
            c = run.finger_position[t, f]
            gap = _box_signed_distance((c[None] - cur) @ Rt[t], half) - run.finger_radius[f]
            step = np.where(gap < 0, np.minimum(-gap / size, MAX_STEP), 0.0)
            cur = cur + step[:, None] * (push / size)[None]
        pos[:, t] = cur
    return pos


def resting_poses(run: Run, extents_m: np.ndarray) -> np.ndarray:
    """(N, T, 7) the boxes of extents (N, 3) m resting at their initial poses throughout."""
    extents_m = np.atleast_2d(np.asarray(extents_m, float))
    R0 = initial_orientation(run)
    pos = initial_position(run, extents_m, R0)
    q = _quat_from_matrix(R0)
    pose = np.concatenate([pos, np.repeat(q[None], len(pos), 0)], 1)
    return np.repeat(pose[:, None], run.n_samples, 1)


def finger_gaps_3d(run: Run, extents_m: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(N, T, F) m: gap between each fingertip sphere and each box of extents (N, 3) m
    placed at poses (N, T, 7)."""
    N, T, F = poses.shape[0], run.n_samples, run.n_fingers
    if not F:
        return np.zeros((N, T, 0))
    if np.array_equal(poses[:, :, 3:], np.broadcast_to(poses[:1, :, 3:], poses[:, :, 3:].shape)):
        # one orientation per sample for every box (the push tracker's): rotate the
        # fingertips and the centres once each, Rᵀ c - Rᵀ p (the same values to rounding)
        R = quat_to_matrix(poses[0, :, 3:])  # (T, 3, 3)
        c_body = np.einsum("tji,tfj->tfi", R, run.finger_position)  # (T, F, 3)
        p_body = c_body[None] - np.einsum("tji,ntj->nti", R, poses[..., :3])[:, :, None, :]
    else:
        R = quat_to_matrix(poses[..., 3:].reshape(-1, 4)).reshape(N, T, 3, 3)
        rel = run.finger_position[None] - poses[:, :, None, :3]  # (N, T, F, 3) world
        p_body = np.einsum("ntji,ntfj->ntfi", R, rel)
    sd = _box_signed_distance(p_body, 0.5 * np.asarray(extents_m, float)[:, None, None, :])
    return np.where(np.isfinite(sd), sd, 0.0) - run.finger_radius[None, None, :]


def touch_inconsistency_3d(run: Run, extents_m: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(N,) m²: how badly each of N boxes (N, 3) m moved along its poses (N, T, 7)
    disagrees with the contact flags: the sum over samples of max(gap, 0)² where a
    fingertip touched and min(gap, 0)² where it did not (data.touch_inconsistency)."""
    if not run.n_fingers:
        return np.zeros(len(poses))
    return touch_inconsistency(run, finger_gaps_3d(run, extents_m, poses))


def start_candidates_3d(runs: list[Run], L: float, resting_extents: np.ndarray, n: int = 1) -> list[Start3D]:
    """Up to n distinct starts, best first, by :func:`touch_inconsistency_3d` summed over
    the runs: push-tracked boxes of extents on :data:`EXTENT_GRID`³ (units of L), each
    picked one refined on the finer grid :data:`EXTENT_REFINE`³ around it, and the
    plain resting start of extents ``resting_extents`` (3,) (units of L).  Each later
    start's extents differ from every earlier one's by more than
    :data:`DISTINCT_EXTENT_RATIO` in some extent, or it is the resting start (the other
    kind of trajectory), so that a restart explores another basin.  With n > 1 the
    resting start is among them (last, if its cost does not rank it higher)."""
    return list(iter_start_candidates_3d(runs, L, resting_extents, n))


def iter_start_candidates_3d(runs: list[Run], L: float, resting_extents: np.ndarray, n: int = 1):
    """The starts of :func:`start_candidates_3d`, each found when it is asked for: the
    grid search of a later one refines about 0.1 s per coarse box near an earlier pick
    (a second or two for a restart that a good first fit makes unnecessary)."""
    g = EXTENT_GRID
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    cost = np.zeros(len(grid))
    for run in runs:
        cost += touch_inconsistency_3d(run, grid * L, push_tracker_3d(run, grid * L))

    def cost_key(extents, costs):
        # ties (an extent no two-sided touch measured leaves the cost unchanged) go to
        # the box nearest the cube of size L: a relative preference of TIE_PREFERENCE
        # per squared log-extent, 1 % at twice or half L, far below the cost steps
        # between grid points that the touches do measure
        return costs * (1 + TIE_PREFERENCE * np.sum(np.log(extents) ** 2, axis=1))

    def refine(e):
        """The best box on the finer grid EXTENT_REFINE³ around extents e (3,) (units of L)."""
        f = EXTENT_REFINE
        boxes = e * np.stack(np.meshgrid(f, f, f, indexing="ij"), -1).reshape(-1, 3)
        tracks = [push_tracker_3d(run, boxes * L) for run in runs]
        c = sum(touch_inconsistency_3d(run, boxes * L, P) for run, P in zip(runs, tracks))
        k = int(np.argmin(cost_key(boxes, c)))
        return boxes[k], [P[k] for P in tracks], float(c[k])

    rest = np.asarray(resting_extents, float)
    rest_cost = sum(float(touch_inconsistency_3d(run, rest[None] * L, resting_poses(run, rest[None] * L))[0])
                    for run in runs)
    all_ext = np.concatenate([rest[None], grid])
    all_cost = np.concatenate([[rest_cost], cost])
    order = np.argsort(cost_key(all_ext, all_cost), kind="stable")
    picked: list[Start3D] = []
    for k in order:
        if len(picked) == n:
            return
        if k == 0 or (n > 1 and len(picked) == n - 1 and all(p.poses is not None for p in picked)):
            cand = Start3D(rest, None, "resting", rest_cost)  # the plain start is always tried
        else:
            def close(e):
                return any(p.poses is not None and np.max(np.abs(np.log(e / p.extents))) <= np.log(
                    DISTINCT_EXTENT_RATIO) for p in picked)

            if close(grid[k - 1]):
                continue
            box, poses, c = refine(grid[k - 1])
            if close(box):  # refined into the neighbourhood of an earlier start
                continue
            cand = Start3D(box, poses, "push-tracked", c)
        picked.append(cand)
        yield cand
    if n > 1 and all(p.poses is not None for p in picked):  # grid used up: the plain start too
        yield Start3D(rest, None, "resting", rest_cost)

"""Replay a recorded run's finger motion in MuJoCo against an exported MJCF object.

This is how a user checks an export: load the MJCF that ``tacest export`` wrote, add
fingertips the way they would (spheres of the run's finger radii, geom class
``tacest_finger`` so that their contacts with the object take the estimated finger
friction), move them along the recorded fingertip positions, simulate, and compare the
object's trajectory with the one tacest estimated.

Fingertips are MuJoCo mocap bodies: kinematic, they go exactly where the run says the
fingertip centre was (linear interpolation between samples, MuJoCo's timestep within
a sample) whatever the object pushes back.  tacest's simulator drives its fingers with
a stiff, force-limited drive instead (tacest.sim3d.world), which lets a finger give
way under more than 30 N; pokes of a free object stay far below that, and the recorded
positions are where the fingers actually were, so following them exactly is the
faithful replay.

Each poke (a row of ``/actions/segments``) starts from the estimated pose and velocity
at its first sample (``reset_each_poke``, the default): the figure is how far the
exported object drifts from the estimate over one poke, not the accumulated drift of a
whole run (the latter with ``reset_each_poke=False``).

Shapes: run with T samples, F fingers; poses (T, 7) [x, y, z, qw, qx, qy, qz] of the
centre of mass, world frame, m.  2-D runs and estimates use the plane mapping of
tacest.export.model (2-D (x, y) is 3-D (x, z)).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from tacest.errors import TacestError
from tacest.export.model import pose2_to_pose3
from tacest.geometry.transforms import quat_angle, quat_to_matrix

#: name prefix of the fingertip bodies the replay adds
FINGER_PREFIX = "tacest_replay_finger"


def add_fingers(mjcf_text: str, finger_radius) -> str:
    """The MJCF ``mjcf_text`` with one mocap fingertip sphere per radius (m) added to its
    worldbody, geom class ``tacest_finger`` (written by tacest export)."""
    root = ET.fromstring(mjcf_text)
    world = root.find("worldbody")
    if world is None:
        raise TacestError("MJCF has no <worldbody>")
    for f, r in enumerate(np.asarray(finger_radius, float).reshape(-1)):
        b = ET.SubElement(world, "body", name=f"{FINGER_PREFIX}{f}", mocap="true", pos="0 0 1")
        ET.SubElement(b, "geom", name=f"{FINGER_PREFIX}{f}", type="sphere", size=repr(float(r)),
                      attrib={"class": "tacest_finger"}, rgba="0.2 0.4 0.9 1")
    return ET.tostring(root, encoding="unicode")


def _finger_positions__world(run) -> np.ndarray:
    """(T, F, 3) m, the run's fingertip centres in the 3-D world frame."""
    p = np.asarray(run.finger_position, float)
    if run.dim == 3:
        return p
    out = np.zeros(p.shape[:2] + (3,))
    out[..., 0], out[..., 2] = p[..., 0], p[..., 1]
    return out


def _velocity3(vel, dim) -> np.ndarray:
    """(T, 6) [v, ω] world frame in 3-D of an estimated velocity (T, 3 or 6)."""
    v = np.asarray(vel, float)
    if dim == 3:
        return v
    out = np.zeros((len(v), 6))
    out[:, 0], out[:, 2] = v[:, 0], v[:, 1]
    out[:, 4] = -v[:, 2]  # counter-clockwise in x-y is about -y in x-z
    return out


@dataclass
class PokeError:
    """Replayed minus estimated trajectory over one poke: positions of the centre of
    mass (m) and rotation angles (rad) over samples [start, stop)."""

    start: int
    stop: int
    position_mean: float
    position_max: float
    position_final: float
    angle_mean: float
    angle_max: float
    angle_final: float


@dataclass
class ReplayResult:
    """pose__world : (T, 7) replayed poses (NaN outside the pokes); pokes : PokeError each."""

    pose__world: np.ndarray
    pokes: list = field(default_factory=list)

    def summary(self) -> dict:
        """Worst and mean over the pokes of the per-poke figures (m, rad)."""
        if not self.pokes:
            return {}
        a = {k: np.array([getattr(p, k) for p in self.pokes]) for k in
             ("position_mean", "position_max", "position_final", "angle_max")}
        return {"pokes": len(self.pokes), "position_mean": float(np.mean(a["position_mean"])),
                "position_max": float(np.max(a["position_max"])),
                "position_final_max": float(np.max(a["position_final"])),
                "angle_max": float(np.max(a["angle_max"]))}


def replay(mjcf_text: str, run, pose__world, velocity__world, segments=None, reset_each_poke=True) -> ReplayResult:
    """Replay ``run``'s finger motion against the object of ``mjcf_text``.

    pose__world : (T, 7) estimated poses (the start of each poke, and the reference);
    velocity__world : (T, 6) estimated [v m/s, ω rad/s], world frame;
    segments : (A, 2) [start, stop) sample indices (default: the run's actions, else the
    whole run).  Returns the replayed poses and the error of each poke.
    """
    import mujoco

    if run.finger_position is None:
        raise TacestError(f"{run.filename or 'run'}: /robot: no fingers to replay")
    p_finger = _finger_positions__world(run)
    T = run.n_samples
    ref = np.asarray(pose__world, float)
    vel = np.asarray(velocity__world, float)
    if ref.shape != (T, 7) or vel.shape != (T, 6):
        raise TacestError(f"{run.filename or 'run'}: the estimated trajectory has {len(ref)} samples, the run {T}")
    if segments is None:
        segments = run.actions.segments if run.actions is not None and len(run.actions.segments) else [(0, T)]
    model = mujoco.MjModel.from_xml_string(add_fingers(mjcf_text, run.finger_radius))
    data = mujoco.MjData(model)
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
    jnt = int(model.body_jntadr[body])
    qa, va = int(model.jnt_qposadr[jnt]), int(model.jnt_dofadr[jnt])
    mocap = [int(model.body_mocapid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"{FINGER_PREFIX}{f}")])
             for f in range(p_finger.shape[1])]
    n_sub = max(1, int(round(run.dt / model.opt.timestep)))
    model.opt.timestep = run.dt / n_sub
    out = np.full((T, 7), np.nan)

    def set_state(k):
        data.qpos[qa:qa + 7] = ref[k]
        data.qvel[va:va + 3] = vel[k, :3]
        data.qvel[va + 3:va + 6] = quat_to_matrix(ref[k, 3:]).T @ vel[k, 3:]  # MuJoCo: body frame
        data.qvel[:va] = 0.0
        for f, m in enumerate(mocap):
            data.mocap_pos[m] = p_finger[k, f]
        mujoco.mj_forward(model, data)

    pokes = []
    started = False
    for start, stop in np.asarray(segments, int):
        if reset_each_poke or not started:
            set_state(start)
            started = True
        out[start] = data.qpos[qa:qa + 7]
        for k in range(start + 1, stop):
            for j in range(1, n_sub + 1):
                s = j / n_sub
                for f, m in enumerate(mocap):
                    data.mocap_pos[m] = (1 - s) * p_finger[k - 1, f] + s * p_finger[k, f]
                mujoco.mj_step(model, data)
            q = np.array(data.qpos[qa:qa + 7])
            q[3:] /= np.linalg.norm(q[3:])
            out[k] = q
        sl = slice(start, stop)
        dp = np.linalg.norm(out[sl, :3] - ref[sl, :3], axis=1)
        da = quat_angle(out[sl, 3:], ref[sl, 3:])
        pokes.append(PokeError(int(start), int(stop), float(np.mean(dp)), float(np.max(dp)), float(dp[-1]),
                               float(np.mean(da)), float(np.max(da)), float(da[-1])))
    return ReplayResult(out, pokes)


def replay_estimate(mjcf_text: str, run, est, run_index: int = 0, reset_each_poke=True) -> ReplayResult:
    """:func:`replay` with the reference trajectory of ``est`` (an Estimate) run
    ``run_index``, in the 3-D frame of the export."""
    r = est.runs[run_index]
    pose = pose2_to_pose3(r.pose) if est.dim == 2 else np.asarray(r.pose, float)
    return replay(mjcf_text, run, pose, _velocity3(r.velocity, est.dim), reset_each_poke=reset_each_poke)

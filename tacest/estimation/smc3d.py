"""Sequential Monte Carlo start of the 3-D estimator for runs without pose observations:
box hypotheses simulated forward under the measured fingertip motion, weighted by the
tactile measurements, resampled through time.

The 3-D counterpart of tacest.estimation.smc2d (whose docstring gives the reasons): the
push tracker that starts 3-D finger-poke fits (tacest.estimation.initial3d) slides the
box along the ground and turns it about the up axis, and never tips it; a box that a
high poke tipped or toppled has no start near its trajectory, and the NLP ends at its
iteration limit or in a wrong basin.  Here N hypotheses (box extents, mass, ground and
finger friction, and the pose and velocity of the box) are moved by
tacest.model.forward3d and weighted at every sample by the contact flags (the fingertip
on the surface where it touched, outside where it did not) and the contact normals;
resampled (systematic) and jittered when the weights concentrate.  The lineage of the
best hypothesis is a start of the NLP (Estimator3D.solve); seeded, so the same runs and
seed give the same start.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from tacest.estimation.data import finger_velocity, touching
from tacest.estimation.initial3d import initial_orientation, initial_position, smoothed_start_track
from tacest.estimation.smc import (ESS_FRACTION, JITTER, REST_OMEGA, REST_SPEED, SIGMA_GAP, SIGMA_NORMAL,
                                   ParticleParameters, fingers_near, subtract_touch_terms)
from tacest.geometry.transforms import quat_from_matrix, quat_from_rotvec, quat_multiply, quat_to_matrix
from tacest.io.run import Run
from tacest.model.forward3d import GROUND_SINK, MAX_STEP, Boxes, World3D, box_finger_geometry

log = logging.getLogger(__name__)

#: s, Savitzky–Golay window of the lineage given to the NLP (a resampled lineage jumps
#: by the jitter, a force-driven one is moved onto the fingertip in small steps)
SMOOTHING_S = 0.07


@dataclass(frozen=True)
class SMC3DSettings:
    """particles : hypotheses; seed : of every random draw; sigma_gap (m), sigma_normal
    (rad) : the likelihood's sigmas (tacest.estimation.smc's)."""

    particles: int = 256
    seed: int = 0
    sigma_gap: float = SIGMA_GAP
    sigma_normal: float = SIGMA_NORMAL


@dataclass
class SMC3DResult:
    """The best hypothesis: extents (3,) m of its box, mass kg, mu_ground, mu_finger,
    poses [(T_i, 7)] per run (its lineage, smoothed, lifted out of the penalty ground),
    its accumulated log likelihood, its largest tilt (deg: the angle between the body's
    up direction now and at the start of its run; a turn about the vertical is no tilt);
    resamples, skipped samples, wall time s, the seed."""

    extents: np.ndarray
    mass: float
    mu_ground: float
    mu_finger: float
    poses: list
    log_likelihood: float
    max_tilt_deg: float
    resamples: int = 0
    skipped: int = 0
    wall_time: float = 0.0
    seed: int = 0


class _Particles(ParticleParameters):
    """The hypotheses' parameters (as box extents (N, 3)), weights and lineage."""

    def boxes(self) -> Boxes:
        return Boxes(0.5 * self.extents, self.mass, self.mu_g, self.mu_f)

    def resample(self, state, hist):
        """Systematic resampling, then jitter; the state (pos, quat, vel, omega_b) and
        the lineage history (T, N, 7) are reordered with the hypotheses."""
        idx = self.resample_parameters()
        j, n, rng = JITTER, self.n, self.rng
        pos, quat, vel, om = (a[idx] for a in state)
        pos = pos + rng.normal(0, j["position"], size=(n, 3))
        quat = quat_multiply(quat, quat_from_rotvec(rng.normal(0, j["angle"], size=(n, 3))))
        vel = vel + rng.normal(0, j["velocity"], size=(n, 3))
        om = om + rng.normal(0, j["omega"], size=(n, 3))
        return (pos, quat, vel, om), hist[:, idx]


def _log_likelihood(run: Run, t, on, hyp: Boxes, R, pos, world, settings) -> np.ndarray:
    """(N,) log likelihood of sample t's contact flags and normals."""
    ll = np.zeros(pos.shape[0])
    valid = ~run.finger_missing_mask[t]
    for f in range(run.n_fingers):
        if not valid[f] or not np.all(np.isfinite(run.finger_position[t, f])):
            continue
        sd, n_w, _ = box_finger_geometry(hyp.half, R, pos, run.finger_position[t, f])
        subtract_touch_terms(ll, on[t, f], sd - world.radius[f], n_w, run.normal[t, f], settings)
    return ll


def _near(run: Run, t, hyp: Boxes, pos, world) -> list:
    """Fingers within reach of any hypothesis at samples t-1 or t."""
    reach = float(np.max(np.linalg.norm(hyp.half, axis=1))) + float(np.max(world.radius)) + 0.01
    return fingers_near(run, t, pos, reach)


def _start_state(run: Run, parts: _Particles, world: World3D):
    R0 = initial_orientation(run)
    n = parts.n
    pos = world.rest_position(0.5 * parts.extents, np.repeat(R0[None], n, 0),
                              initial_position(run, parts.extents, R0))
    quat = np.repeat(quat_from_matrix(R0)[None], n, 0)
    return pos, quat, np.zeros((n, 3)), np.zeros((n, 3))


def _run_filter(run: Run, parts: _Particles, settings, stats) -> np.ndarray:
    """Filter one run (its box starts at rest at the run's initial pose); returns the
    lineage history (T, N, 7) [position m, quaternion]."""
    world = World3D(run.up, run.ground_height, run.gravity, run.finger_radius)
    T = run.n_samples
    hyp = parts.boxes()
    state = _start_state(run, parts, world)
    hist = np.zeros((T, parts.n, 7))
    hist[0] = np.concatenate(state[:2], 1)
    on = touching(run)
    v_f = finger_velocity(run)
    force_driven = run.force is not None
    n_sub = max(1, int(math.ceil(run.dt / MAX_STEP - 1e-9)))
    h = run.dt / n_sub
    resting = True
    for t in range(1, T):
        pos, quat, vel, om = state
        near = _near(run, t, hyp, pos, world)
        if not near and resting:
            hist[t] = hist[t - 1]
            stats["skipped"] += 1
            continue
        pushing = [f for f in near if on[t, f] and np.all(np.isfinite(run.normal[t, f]))]
        if force_driven:  # the measured force at the measured contact point
            forces = [(run.finger_position[t, f] - world.radius[f] * run.normal[t, f], run.force[t, f])
                      for f in pushing]
            pos, quat, vel, om, _ = world.advance(hyp, pos, quat, vel, om, h, n_sub, forces=forces)
        else:  # kinematic fingertips push by penetration, moving from sample t-1 to t
            kin = [(f, run.finger_position[t, f], v_f[t, f]) for f in near]
            pos, quat, vel, om, _ = world.advance(hyp, pos, quat, vel, om, h, n_sub, fingers=kin,
                                                  start_centres=[run.finger_position[t - 1, f] for f in near])
        R = quat_to_matrix(quat)
        ll = _log_likelihood(run, t, on, hyp, R, pos, world, settings)
        ll = np.where(np.isfinite(ll), ll, -1e12)
        if force_driven:  # moved onto the touching fingertips for the samples to come
            for f in pushing:
                sd, n_w, _ = box_finger_geometry(hyp.half, R, pos, run.finger_position[t, f])
                pos = pos + (sd - world.radius[f])[:, None] * n_w
        bad = ~(np.all(np.isfinite(pos), 1) & np.all(np.isfinite(quat), 1) & np.all(np.isfinite(vel), 1)
                & np.all(np.isfinite(om), 1))
        if bad.any():  # a hypothesis the explicit steps blew up: out of the running
            ll[bad] = -1e12
            pos[bad], quat[bad], vel[bad], om[bad] = hist[t - 1, bad, :3], hist[t - 1, bad, 3:], 0.0, 0.0
        state = (pos, quat, vel, om)
        hist[t] = np.concatenate([pos, quat], 1)
        resting = bool(np.all(np.linalg.norm(vel, axis=1) < REST_SPEED)
                       and np.all(np.linalg.norm(om, axis=1) < REST_OMEGA))
        parts.log_w += ll
        parts.log_lik += ll
        if parts.ess() < ESS_FRACTION * parts.n:
            state, hist = parts.resample(state, hist)
            hyp = parts.boxes()
            stats["resamples"] += 1
    return hist


def _as_start(run: Run, poses) -> np.ndarray:
    """(T, 7) a lineage as a start: lifted out of the forward model's ground sink (the
    estimator's ground is rigid), quaternion signs made continuous, smoothed."""
    from tacest.dynamics.rigid3d import align_quaternion_signs

    P = np.array(poses, float)
    P[:, :3] += GROUND_SINK * np.asarray(run.up, float)[None] / np.linalg.norm(run.up)
    P[:, 3:] /= np.linalg.norm(P[:, 3:], axis=1, keepdims=True)
    P[:, 3:] = align_quaternion_signs(P[:, 3:])
    window = max(5, int(round(SMOOTHING_S / run.dt)) | 1)
    return smoothed_start_track(P, window)


def _max_tilt_deg(runs: list[Run], poses: list) -> float:
    """deg: the largest angle between the ground normal seen from the body at a sample
    and at its run's first sample, over the runs' (T, 7) poses."""
    out = 0.0
    for run, P in zip(runs, poses):
        up = np.asarray(run.up, float) / np.linalg.norm(run.up)
        u_b = np.einsum("tji,j->ti", quat_to_matrix(P[:, 3:]), up)  # Rᵀ up per sample
        out = max(out, float(np.degrees(np.max(np.arccos(np.clip(u_b @ u_b[0], -1.0, 1.0))))))
    return out


def smc_start_3d(runs: list[Run], L: float, m0: float, extents0, settings: SMC3DSettings = SMC3DSettings()
                 ) -> SMC3DResult:
    """Filter every run in turn (the hypotheses' parameters carry over from run to run;
    each run's box starts at rest at the run's initial pose) and return the best
    hypothesis and its lineage.

    L, m0 : the estimator's length (m) and mass (kg) scales; extents0 : (3,) m, the
    push tracker's best box (half the hypotheses start around it)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(settings.seed)
    parts = _Particles(int(settings.particles), rng, L, m0, any(r.force is not None for r in runs),
                       np.asarray(extents0, float))
    stats = {"resamples": 0, "skipped": 0}
    last = None
    for run in runs:
        last = _run_filter(run, parts, settings, stats)
    best = int(np.argmax(parts.log_lik))
    poses = []
    for i, run in enumerate(runs):  # earlier runs re-filtered with the best hypothesis alone (as smc2d)
        if i == len(runs) - 1:
            poses.append(last[:, best].copy())
        else:
            single = parts.take([best])
            single.rng = np.random.default_rng(settings.seed + 1 + i)
            poses.append(_run_filter(run, single, settings, {"resamples": 0, "skipped": 0})[:, 0].copy())
    poses = [_as_start(run, P) for run, P in zip(runs, poses)]
    ext = parts.extents[best].copy()
    result = SMC3DResult(extents=ext, mass=float(parts.mass[best]), mu_ground=float(parts.mu_g[best]),
                         mu_finger=float(parts.mu_f[best]), poses=poses, log_likelihood=float(parts.log_lik[best]),
                         max_tilt_deg=_max_tilt_deg(runs, poses), resamples=stats["resamples"], skipped=stats["skipped"],
                         wall_time=time.perf_counter() - t0, seed=int(settings.seed))
    log.info(f"sampled start (3-D): {parts.n} hypotheses, {stats['resamples']} resamples, {stats['skipped']} idle "
             f"samples skipped, best box {np.round(ext * 1e3, 1)} mm, tilted up to {result.max_tilt_deg:.0f} deg, "
             f"log likelihood {result.log_likelihood:.4g} ({result.wall_time:.1f} s)")
    return result

"""Sequential Monte Carlo start of the 2-D estimator: object hypotheses simulated forward
under the measured fingertip motion, weighted by the tactile measurements, resampled
through time.

Why.  A gradient-based NLP started from a sliding guess cannot find a trajectory that
tipped or toppled: it converges to a wrong basin (a short box that slid, heavy friction,
a light mass) whose objective looks fine.  Something must first follow the object through
its tips and topples: here N hypotheses (shape extents, mass, ground and finger friction,
and the pose and velocity of the object) are moved by a fast forward model
(tacest.model.forward2d: penalty contacts; where the run measures forces, the measured
force acts at the measured contact point and each hypothesis is moved onto the touching
fingertip; without forces the fingertips push by penetration) and weighted at every
sample by how well they explain the contact flags (the fingertip on the surface where
it touched, outside where it did not) and the contact normals.  When the weights concentrate (effective sample size
below ESS_FRACTION · N) the hypotheses are resampled (systematic resampling) and jittered
(small random changes of the parameters and the state: the filter keeps exploring around
what explains the data).  The lineage of the best hypothesis (highest accumulated log
likelihood) gives the NLP its start: shape, parameters and every run's trajectory
(tacest.estimation.estimator.ImplicitEstimator.smc_start).

The sampler is seeded (:class:`SMCSettings` seed): the same runs and seed give the same
start.  Samples where no fingertip is near any hypothesis and every hypothesis is at rest
are skipped (nothing moves, nothing is measured).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from tacest.estimation.data import finger_velocity, touching
from tacest.estimation.initial import initial_extents, initial_pose_range, smooth_quadratic
from tacest.io.run import Run
from tacest.estimation.smc import (ESS_FRACTION, JITTER, REST_OMEGA, REST_SPEED, SIGMA_GAP, SIGMA_NORMAL,
                                   ParticleParameters, fingers_near, subtract_touch_terms)
from tacest.model.forward2d import GROUND_SINK, MAX_STEP, World2D, box_hypotheses, finger_geometry

log = logging.getLogger(__name__)

#: copies of the best hypothesis that re-filter an earlier run whose first touch leaves
#: the resting position a range (smc_start): evenly spread over it, 4 mm apart for a
#: 60 mm range
REFILTER_COPIES = 16


@dataclass(frozen=True)
class SMCSettings:
    """particles : hypotheses; seed : of every random draw; sigma_gap (m), sigma_normal
    (rad) : the likelihood's sigmas."""

    particles: int = 256
    seed: int = 0
    sigma_gap: float = SIGMA_GAP
    sigma_normal: float = SIGMA_NORMAL


@dataclass
class SMCResult:
    """The best hypothesis: extents (2,) m of its box, mass kg, inertia kg·m², mu_ground,
    mu_finger, poses [(T_i, 3)] per run (its lineage), its accumulated log likelihood;
    resamples, skipped samples, wall time s."""

    extents: np.ndarray
    mass: float
    inertia: float
    mu_ground: float
    mu_finger: float
    poses: list
    log_likelihood: float
    resamples: int = 0
    skipped: int = 0
    wall_time: float = 0.0
    history: dict = field(default_factory=dict)
    #: the seed of the sampler's draws
    seed: int = 0


class _Particles(ParticleParameters):
    """The hypotheses' parameters (as box extents (N, 2)), weights and lineage."""

    def hypotheses(self):
        return box_hypotheses(self.extents[:, 0], self.extents[:, 1], self.mass, self.mu_g, self.mu_f)

    def resample(self, pose, vel, hist):
        """Systematic resampling, then jitter; pose, vel (N, 3) and the lineage history
        (T, N, 3) are reordered with the hypotheses."""
        idx = self.resample_parameters()
        j = JITTER
        pose = pose[idx] + self.rng.normal(0, 1, size=(self.n, 3)) * [j["position"], j["position"], j["angle"]]
        vel = vel[idx] + self.rng.normal(0, 1, size=(self.n, 3)) * [j["velocity"], j["velocity"], j["omega"]]
        return pose, vel, hist[:, idx]


def _log_likelihood(run: Run, t, on, hyp, pose, world, settings) -> np.ndarray:
    """(N,) log likelihood of sample t's contact flags and normals.  (Where the run
    measures forces they drive the hypotheses, so they do not weigh them.)"""
    ll = np.zeros(pose.shape[0])
    valid = ~run.finger_missing_mask[t]
    for f in range(run.n_fingers):
        if not valid[f]:
            continue
        sd, n_w, _ = finger_geometry(hyp, pose, run.finger_position[t, f])
        subtract_touch_terms(ll, on[t, f], sd - world.radius[f], n_w, run.normal[t, f], settings)
    return ll


def _snap(run: Run, t, pushing, hyp, pose, world) -> np.ndarray:
    """Poses moved along each touching fingertip's normal until it sits on the surface:
    a force-driven hypothesis is tied to the fingertip only by the measurements, and a
    slightly wrong friction or mass would let it drift away from a long push (the
    proposal follows the contact; the weights judge the rest)."""
    for f in pushing:
        sd, n_w, _ = finger_geometry(hyp, pose, run.finger_position[t, f])
        gap = sd - world.radius[f]
        pose = pose.copy()
        pose[:, :2] += gap[:, None] * n_w
    return pose


def _near(run: Run, t, hyp, pose, world) -> list:
    """Fingers within reach of any hypothesis at samples t-1 or t."""
    reach = float(np.max(np.linalg.norm(hyp.vertices, axis=-1))) + float(np.max(world.radius)) + 0.01
    return fingers_near(run, t, pose[:, :2], reach)


def _run_filter(run: Run, parts: _Particles, settings, stats, even_spread: bool = False) -> np.ndarray:
    """Filter one run (its object starts at rest); returns the lineage history (T, N, 3).
    Where the run's first touch leaves the resting position a range
    (initial.initial_pose_range), the hypotheses start spread over it: drawn uniformly,
    or with ``even_spread`` evenly from one end to the other."""
    world = World2D(run.up, run.ground_height, run.gravity, run.finger_radius)
    T = run.n_samples
    hyp = parts.hypotheses()
    ext = parts.extents
    # where each hypothesis rests before the first touch: a first touch on the top face
    # leaves the centre anywhere under it (uniform over its half range)
    start = [initial_pose_range(run, w, h) for w, h in ext]
    x0 = np.array([pose[:2] @ world.t_g for pose, _ in start])
    half_range = np.array([r for _, r in start])
    if np.any(half_range > 0):
        u = np.linspace(-1.0, 1.0, len(x0)) if even_spread else parts.rng.uniform(-1.0, 1.0, size=len(x0))
        x0 = x0 + u * half_range
    pose = world.rest_pose(hyp.vertices, x0)
    vel = np.zeros_like(pose)
    hist = np.zeros((T, parts.n, 3))
    hist[0] = pose
    on = touching(run)
    v_f = finger_velocity(run) if run.n_fingers else None
    n_sub = max(1, int(math.ceil(run.dt / MAX_STEP - 1e-9)))
    h = run.dt / n_sub
    resting = True
    for t in range(1, T):
        near = _near(run, t, hyp, pose, world) if run.n_fingers else []
        if not near and resting:
            hist[t] = pose
            stats["skipped"] += 1
            continue
        force_driven = run.force is not None
        pushing = [f for f in near if on[t, f]]
        if force_driven:  # the measured force at the measured contact point
            forces = [(run.finger_position[t, f] - world.radius[f] * np.nan_to_num(run.normal[t, f]),
                       run.force[t, f]) for f in pushing]
            pose, vel, _ = world.advance(hyp, pose, vel, h, n_sub, forces=forces)
        else:  # kinematic fingertips push by penetration, moving from sample t-1 to t
            kin = [(f, run.finger_position[t, f], v_f[t, f]) for f in near]
            pose, vel, _ = world.advance(hyp, pose, vel, h, n_sub, fingers=kin,
                                         start_centres=[run.finger_position[t - 1, f] for f in near])
        # weighed where the hypothesis' own dynamics put it, then (force-driven) moved
        # onto the touching fingertips for the samples to come
        ll = _log_likelihood(run, t, on, hyp, pose, world, settings)
        ll = np.where(np.isfinite(ll), ll, -1e12)
        if force_driven:
            pose = _snap(run, t, pushing, hyp, pose, world)
        hist[t] = pose
        resting = bool(np.all(np.hypot(vel[:, 0], vel[:, 1]) < REST_SPEED) and np.all(np.abs(vel[:, 2]) < REST_OMEGA))
        parts.log_w += ll
        parts.log_lik += ll
        if parts.ess() < ESS_FRACTION * parts.n:
            pose, vel, hist = parts.resample(pose, vel, hist)
            hyp = parts.hypotheses()
            stats["resamples"] += 1
    return hist


#: s, window of the local quadratic that smooths a lineage for the NLP's start: the
#: force-driven hypotheses are moved onto the fingertip in small steps, whose differences
#: would be velocity spikes (as observed poses' noise would: initial.OBSERVED_SMOOTHING_S)
SMOOTHING_S = 0.07


def _as_start(run: Run, poses) -> np.ndarray:
    """(T, 3) a lineage as a start: lifted out of the forward model's ground sink (the
    estimator's ground is rigid) and smoothed by a local quadratic over SMOOTHING_S."""
    P = np.array(poses, float)
    P[:, :2] += GROUND_SINK * np.asarray(run.up, float)[None]
    P[:, 2] = np.unwrap(P[:, 2])
    return smooth_quadratic(P, run.dt, SMOOTHING_S)


def smc_start(runs: list[Run], L: float, m0: float, settings: SMCSettings = SMCSettings()) -> SMCResult:
    """Filter every run in turn (the hypotheses' parameters carry over from run to run;
    each run's object starts at rest) and return the best hypothesis and its lineage.

    L, m0 : the estimator's length (m) and mass (kg) scales (the hypotheses' ranges)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(settings.seed)
    w0, h0 = initial_extents(runs, L)
    parts = _Particles(int(settings.particles), rng, L, m0, any(r.force is not None for r in runs),
                       np.array([w0, h0]))
    stats = {"resamples": 0, "skipped": 0}
    histories = []
    for i, run in enumerate(runs):
        hist = _run_filter(run, parts, settings, stats)
        # the lineage of earlier runs follows the resampling of later ones: the hypotheses
        # keep their parameters, so earlier histories are reindexed with them (below, by
        # re-running the choice on the last run's population)
        histories.append(hist)
    best = int(np.argmax(parts.log_lik))
    # earlier runs' histories were reindexed only while they were filtered; the final
    # population's ancestry into them is not tracked, so their trajectories are taken
    # from the hypothesis with the same parameters' best lineage: the last run's best
    # carries its own, the earlier ones are re-filtered with it alone
    poses = []
    for i, run in enumerate(runs):
        if i == len(runs) - 1:
            poses.append(histories[i][:, best].copy())
        else:
            # where the run's first touch leaves the resting position a range, copies of
            # the best hypothesis start evenly over it and the most likely is followed
            spread = initial_pose_range(run, *parts.extents[best])[1] > 0
            single = parts.take([best] * (REFILTER_COPIES if spread else 1))
            single.rng = np.random.default_rng(settings.seed + 1 + i)
            single.log_w, single.log_lik = np.zeros(single.n), np.zeros(single.n)
            hist = _run_filter(run, single, settings, {"resamples": 0, "skipped": 0}, even_spread=True)
            poses.append(hist[:, int(np.argmax(single.log_lik))].copy())
    poses = [_as_start(run, P) for run, P in zip(runs, poses)]
    ext = parts.extents[best]
    mass = float(parts.mass[best])
    result = SMCResult(extents=ext.copy(), mass=mass, inertia=mass * float(ext[0] ** 2 + ext[1] ** 2) / 12,
                       mu_ground=float(parts.mu_g[best]), mu_finger=float(parts.mu_f[best]), poses=poses,
                       log_likelihood=float(parts.log_lik[best]), resamples=stats["resamples"],
                       skipped=stats["skipped"], wall_time=time.perf_counter() - t0, seed=int(settings.seed))
    log.info(f"sampled start: {parts.n} hypotheses, {stats['resamples']} resamples, {stats['skipped']} idle samples "
             f"skipped, best box {np.round(ext * 1e3, 1)} mm, log likelihood {result.log_likelihood:.4g} "
             f"({result.wall_time:.1f} s)")
    return result

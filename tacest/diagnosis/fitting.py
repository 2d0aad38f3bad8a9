"""Fits for the diagnosis, all through the 2-D estimator's one staged solve
(tacest.estimation.estimator.ImplicitEstimator): the estimator's own cold solve
(:func:`fit_estimator`), and fits from an earlier estimate's parameters and trajectories
with some parameters held (:func:`fit_local`: warm-started training fits, held-out fits
with the trained parameters pinned).

Both return a :class:`FitResult` whose estimate has per-sample residuals;
:func:`weighted_objective` sums them the same way for every candidate.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from tacest.errors import SolveFailedError, TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import pose_observation_columns
from tacest.estimation.estimator import PIN_MODES, ImplicitEstimator, estimate_2d, theta_of, warm_start
from tacest.estimation.initial import start_shape_candidates
from tacest.io.estimate import Estimate, RunEstimate
from tacest.model.stage2d import PENALTY_TERMS, TERMS

log = logging.getLogger(__name__)


class CandidateUnavailable(TacestError):
    """A candidate effect cannot be fitted by this version of the estimator."""


def weighted_objective(est: Estimate, config: EstimatorConfig, runs_index=None, terms=None) -> float:
    """Σ over runs, samples and loss terms (``terms``, default every one) of weight ×
    per-sample residual value (the NLP objective without its parameter priors), from an
    estimate's residuals."""
    w = config.weights
    total = 0.0
    idx = range(len(est.runs)) if runs_index is None else runs_index
    for i in idx:
        res = est.runs[i].residuals
        for t in TERMS if terms is None else terms:
            if t in res:
                total += float(getattr(w, t)) * float(np.sum(res[t]))
    return total


def occam_objective(est: Estimate, config: EstimatorConfig) -> float:
    """The Occam part of :func:`weighted_objective` (0 where ``weights.occam`` is 0)."""
    return weighted_objective(est, config, terms=PENALTY_TERMS)


@dataclass
class FitResult:
    """One fit: the estimate, the runs it was fitted to (after any transform; [] in a fit
    a task returns, whose runs its caller has), its scaled theta (what a later fit can
    pin), its wall time (s), notes for the report, and ``log``: progress messages of a fit
    made where it ran (a Dask worker), for the log of the process that asked for it."""

    estimate: Estimate
    runs: list
    theta: Optional[np.ndarray] = None
    wall_time: float = 0.0
    effects: tuple = ()
    notes: list = field(default_factory=list)
    log: list = field(default_factory=list)


def observed_warm_runs(runs: list, fallback: list) -> list:
    """Per run, a RunEstimate whose trajectory is the run's pose observations as
    recorded (no smoothing: an impact or a bounce keeps its corner; rows not observed
    take ``fallback[i]``'s poses), velocities by differences; ``fallback[i]`` itself for
    a run without pose observations."""
    out = []
    for run, fb in zip(runs, fallback):
        if run.pose_obs is None or fb is None:
            out.append(fb)
            continue
        obs, seen = pose_observation_columns(run)
        pose = np.array(fb.pose, float)
        rows = seen[:, 0] > 0
        pose[rows, :3] = obs[rows]
        vel = np.zeros_like(pose)
        vel[1:] = np.diff(pose, axis=0) / run.dt
        out.append(RunEstimate(pose=pose, velocity=vel, impulses=dict(fb.impulses), source_file=fb.source_file,
                               source_sha256=fb.source_sha256))
    return out


def fit_local(runs: list, shape: str, config: EstimatorConfig, warm: Estimate = None, warm_runs: list = None,
              pinned: np.ndarray = None, pin: str = "all", information: bool = False,
              accept_budget: bool = False, effects=(), hold_warm: bool = False) -> FitResult:
    """Fit ``runs`` from a warm start (or the estimator's own single best start).

    warm : Estimate whose parameters (and, per run, ``warm_runs[i]`` trajectories) start
        the solve: with warm trajectories only the last homotopy stage runs (after the
        impulses); without it the estimator's own cold start is used;
    pinned : scaled theta (a previous FitResult.theta) held fixed: all of it (``pin``
        "all"), its shape part only (``pin`` "shape"), or all but the shape (``pin``
        "physics": mass, inertia, frictions, effect parameters);
    accept_budget : keep the last iterate of a final stage that used up its iteration
        budget (config.solver.max_iter), reporting IPOPT's status;
    effects : effects of the fitted model (tacest.model.registry); parameters the warm
        estimate lacks start at "no effect";
    hold_warm : hold every parameter at the warm estimate's values: only trajectories and
        impulses are fitted (the first half of a start at a given effect strength).
    Raises SolveFailedError when IPOPT fails.
    """
    t0 = time.perf_counter()
    if pin not in PIN_MODES:
        raise TacestError(f"internal: pin must be one of {PIN_MODES}, got {pin!r}")
    if hold_warm and (warm is None or pinned is not None):
        raise TacestError("internal: hold_warm needs a warm estimate and no pinned theta")
    est = ImplicitEstimator(runs, shape, config, effects=tuple(effects), pinned_theta=pinned, pin=pin)
    if hold_warm:
        est.pinned_theta, est.pin = theta_of(est, warm, "the warm estimate", missing_effects_at_zero=True), "all"
    notes = []
    warm_given = warm is not None and any(w is not None for w in (warm_runs or []))
    try:
        if warm is not None:
            z0 = warm_start(est, warm, warm_runs or [None] * len(runs))
            out = est.solve_from(z0, last_only=warm_given, accept_budget=accept_budget)
        else:
            out = _cold_solve(est, accept_budget)
    except SolveFailedError as exc:
        if warm is None:
            raise
        # a warm start can land in a region where IPOPT stalls: try once from the
        # estimator's own consistent start (same budget), and say so
        notes.append(f"warm start failed ({exc}); solved from the estimator's start")
        log.info(notes[-1])
        out = _cold_solve(est, accept_budget)
    if any("(retry)" in s.name for s in out.stages):
        notes.append("IPOPT failed to step in a final stage, which was redone once with a larger ridge")
    estimate = est.result(out, time.perf_counter() - t0, information=information, penalty_shift=False)
    theta = np.asarray(out.z[: est.problem.n_theta], float).copy()
    return FitResult(estimate=estimate, runs=list(runs), theta=theta, wall_time=estimate.wall_time,
                     effects=tuple(effects), notes=notes)


def _cold_solve(est: ImplicitEstimator, accept_budget: bool):
    """The estimator's single best start (start shape, push-tracker trajectories) and
    every homotopy stage; a pinned shape replaces the start shape."""
    pr = est.problem
    if est.pinned_theta is None or est.pin == "physics":
        s0 = start_shape_candidates(pr, est.runs, est.scales, est.s0, 1)[0]
    else:
        s0 = np.asarray(est.pinned_theta[: pr.n_shape], float)
    return est.solve_from(est.own_start(s0), accept_budget=accept_budget)


def fit_estimator(runs: list, shape: str, config: EstimatorConfig, effects=()) -> FitResult:
    """The estimator's own fit (estimate_2d: its starts and restarts) with ``effects``."""
    t0 = time.perf_counter()
    est = estimate_2d(runs, shape, config, effects=tuple(effects))
    return FitResult(estimate=est, runs=list(runs), wall_time=time.perf_counter() - t0, effects=tuple(effects))


def check_fit(fit: FitResult, what: str):
    if not fit.estimate.success:
        raise SolveFailedError(f"{what}: IPOPT status {fit.estimate.solver_status}")

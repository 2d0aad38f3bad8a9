"""Fits for the diagnosis: training fits (warm-started) and held-out fits with the
parameters held fixed.

Two back ends, chosen once per diagnosis so that every candidate is fitted and
evaluated the same way:

``estimator``
    ``tacest.estimation.estimator.estimate_runs(..., effects=(...), fixed=EST)`` when
    the estimator offers those keywords (model augmentations inside the NLP; ``fixed``
    holds every parameter of EST and fits trajectories and impulses only).
``local``
    the estimator as it is (no effect parameters in the NLP), driven from here: a
    subclass of :class:`ImplicitEstimator` that (a) starts from a given estimate
    (warm start: parameters and trajectories), and (b) can pin the shared parameters
    (shape, mass, inertia, frictions) at the values of a training fit, so that only
    trajectories and impulses of the held-out data are fitted.  Only the data-transform
    candidates (``latency``, ``time_scale``) and ``none`` can be fitted this way.

Both return :class:`tacest.io.estimate.Estimate` objects with per-sample residuals;
:func:`weighted_objective` sums them the same way for every candidate.
"""

from __future__ import annotations

import copy
import inspect
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from tacest.errors import SolveFailedError, TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.estimator import PIN_HALF_WIDTH  # the interval that pins a parameter
from tacest.io.estimate import Estimate, RunEstimate


#: IPOPT statuses of a solve that ran out of its iteration or time budget: with
#: ``accept_budget`` its last iterate is used (and reported with this status)
BUDGET_STATUSES = ("Maximum_Iterations_Exceeded", "Maximum_CpuTime_Exceeded")


#: IPOPT statuses of a final stage after which the stage is redone once from its last
#: iterate with the Gauss–Newton Hessian and ridge RETRY_RIDGE (LocalEstimator.solve_from)
RETRY_STATUSES = ("Error_In_Step_Computation", "Restoration_Failed")
#: Levenberg–Marquardt ridge (scaled units) of that retry: the estimator's default before
#: it was lowered to 0.05 for speed; it keeps the steps local where IPOPT failed to step
RETRY_RIDGE = 1.0
#: what a local fit can hold fixed (see fit_local)
PIN_MODES = ("all", "shape", "physics")


class CandidateUnavailable(TacestError):
    """A candidate effect cannot be fitted by this version of the estimator."""


def _noop(*_a, **_k):
    pass


def local_supports_effects() -> bool:
    """True when ``ImplicitEstimator`` takes ``effects=`` (the local back end can then fit
    the NLP augmentations with warm starts)."""
    from tacest.estimation.estimator import ImplicitEstimator

    return "effects" in inspect.signature(ImplicitEstimator.__init__).parameters


def estimator_supports_effects() -> bool:
    """True when ``estimate_runs`` takes ``effects=`` and ``fixed=`` (NLP augmentations)."""
    from tacest.estimation.estimator import estimate_runs

    params = inspect.signature(estimate_runs).parameters
    return "effects" in params and "fixed" in params


def weighted_objective(est: Estimate, config: EstimatorConfig, runs_index=None, terms=None) -> float:
    """Σ over runs, samples and loss terms (``terms``, default every one) of weight ×
    per-sample residual value (the NLP objective without its parameter priors), from an
    estimate's residuals."""
    from tacest.estimation.problem import TERMS

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
    from tacest.estimation.problem import PENALTY_TERMS

    return weighted_objective(est, config, terms=PENALTY_TERMS)


@dataclass
class FitResult:
    """One fit: the estimate, the runs it was fitted to (after any transform), the
    pinned-parameter vector of the local back end (scaled theta), its wall time (s)."""

    estimate: Estimate
    runs: list
    theta: Optional[np.ndarray] = None
    wall_time: float = 0.0
    backend: str = "local"
    effects: tuple = ()
    notes: list = field(default_factory=list)


# ------------------------------------------------------------------------------------
# local back end


def _local_estimator_class():
    """The subclass is defined lazily (CasADi and the estimator import on first use)."""
    from tacest.estimation.estimator import ImplicitEstimator

    class LocalEstimator(ImplicitEstimator):
        """ImplicitEstimator with a warm start and optional pinned shared parameters."""

        def __init__(self, runs, shape_spec, config, echo, pinned_theta=None, pin="all", effects=()):
            # its own copy: solve_from may change the ridge of a retry
            super().__init__(runs, shape_spec, copy.deepcopy(config or EstimatorConfig()), echo,
                             effects=tuple(effects))
            self.pinned_theta = None if pinned_theta is None else np.asarray(pinned_theta, float)
            self.pin = pin
            self.z = None
            self.retried = False

        def variable_bounds(self):
            lbx, ubx = super().variable_bounds()
            if self.pinned_theta is None:
                return lbx, ubx
            pr = self.problem
            th = self.pinned_theta
            lbx0, ubx0 = lbx.copy(), ubx.copy()
            if self.pin == "shape":
                # the shape alone: the lifted vertices follow from the constraint phys = phys(theta)
                lbx[: pr.n_shape] = ubx[: pr.n_shape] = th[: pr.n_shape]
            elif self.pin == "physics":
                # everything but the shape (mass, inertia, frictions, effect parameters)
                lbx[pr.n_shape: pr.n_theta] = ubx[pr.n_shape: pr.n_theta] = th[pr.n_shape:]
            else:
                phys = np.asarray(pr.phys_sx(th, self.scales.L, self.scales.m0)).reshape(-1)
                lbx[: pr.n_theta] = ubx[: pr.n_theta] = th
                a = pr.phys_offset
                lbx[a: a + pr.n_phys] = ubx[a: a + pr.n_phys] = phys
            if self.shape.name != "box" and self.pin != "physics":
                # a pinned shape has its orientation: no gauge on the start angle
                g = pr.offsets[0]["Q"][0] + 2
                lbx[g], ubx[g] = -np.inf, np.inf
            # pinned = a tiny interval, not equal bounds (see PIN_HALF_WIDTH)
            pinned = (lbx == ubx) & ~(lbx0 == ubx0)
            half = PIN_HALF_WIDTH * np.maximum(1.0, np.abs(lbx[pinned]))
            lbx[pinned] -= half
            ubx[pinned] += half
            return lbx, ubx

        def solve_from(self, z0, cold: bool, accept_budget: bool = False):
            """Staged solve from z0: impulses alone, then every homotopy stage (cold) or
            only the last one (warm: z0 is already a solution of a nearby problem).

            accept_budget: a final stage that stops at its iteration budget
            (Maximum_Iterations_Exceeded) keeps its last iterate and its status, instead
            of raising; success stays False for it."""
            from tacest.estimation.solver import FATAL_STATUSES, SUCCESS_STATUSES, SolveOutcome, check_success

            cfg = self.config.solver
            pr = self.problem
            self.z = np.asarray(z0, float).copy()
            hom = list(cfg.homotopy)
            stages = hom if cold else hom[-1:]
            plan = [("impulses", *stages[0], "impulses")]
            plan += [(f"homotopy {k + 1}/{len(stages)}", *s, "all") for k, s in enumerate(stages)]
            lam_x = lam_g = None
            infos = []
            for label, eps, w, wd, which in plan:
                lbx, ubx = self.variable_bounds()
                if which == "impulses":
                    self.z = self.settle_states(self.z, self.params(eps, w, wd))
                    lbx, ubx = self.impulse_only_bounds(lbx, ubx)
                self.z = np.clip(self.z, lbx, ubx)
                final = label == plan[-1][0]
                mode = cfg.hessian
                if mode == "gauss-newton-then-exact":
                    mode = "exact" if final and len(plan) > 2 else "gauss-newton"
                max_iter = cfg.max_iter if final else cfg.stage_max_iter
                p = self.params(eps, w, wd)
                sol, info = self.built.solve(self.z, p, lbx, ubx, pr.lbg, pr.ubg, lam_x, lam_g, label=label,
                                             echo=self.echo, hessian=mode, max_iter=max_iter)
                self.echo(f"stage {label}: {info.status}, {info.iterations} iterations, "
                          f"objective {info.objective:.6g}, {info.wall_time:.1f} s")
                x_last = np.asarray(sol["x"]).reshape(-1)
                if final and info.status in RETRY_STATUSES and np.all(np.isfinite(x_last)):
                    # IPOPT could not compute a step (a KKT system it could not correct):
                    # redo the stage once from its last iterate with the Gauss–Newton model
                    # and a larger Levenberg–Marquardt ridge (shorter, safer steps), same
                    # budget; the fit reports it in its notes
                    infos.append(info)
                    self.retried = True
                    ridge0 = self.config.solver.hessian_ridge
                    try:
                        self.config.solver.hessian_ridge = max(RETRY_RIDGE, ridge0)
                        p_retry = self.params(eps, w, wd)
                    finally:
                        self.config.solver.hessian_ridge = ridge0
                    sol, info = self.built.solve(np.clip(x_last, lbx, ubx), p_retry, lbx, ubx, pr.lbg, pr.ubg, None,
                                                 None, label=label + " (retry)", echo=self.echo,
                                                 hessian="gauss-newton", max_iter=max_iter)
                    self.echo(f"stage {label} (retry): {info.status}, {info.iterations} iterations, "
                              f"objective {info.objective:.6g}, {info.wall_time:.1f} s")
                infos.append(info)
                budget_hit = final and accept_budget and info.status in BUDGET_STATUSES
                if (final and not budget_hit) or which == "impulses" or info.status in FATAL_STATUSES:
                    check_success(info)
                self.z = np.asarray(sol["x"]).reshape(-1)
                if which == "all":
                    lam_x = np.asarray(sol["lam_x"]).reshape(-1)
                    lam_g = np.asarray(sol["lam_g"]).reshape(-1)
            self.p_final = self.params(*plan[-1][1:4])
            last = infos[-1]
            return SolveOutcome(z=self.z, lam_g=lam_g, lam_x=lam_x, status=last.status,
                                success=last.status in SUCCESS_STATUSES,
                                iterations=sum(s.iterations for s in infos), wall_time=sum(s.wall_time for s in infos),
                                objective=last.objective, stages=infos)

    return LocalEstimator


def theta_from_estimate(problem, scales, estimate: Estimate) -> np.ndarray:
    """Scaled theta [shape s, log(m/m0), log(I/I_uniform), mu_ground, mu_finger, effect
    parameters] of an estimate (estimator.core_theta_of, then the effect block).
    Effect parameters the estimate does not have (a plain fit warm-starting an
    augmented model) start at "no effect" (scaled 0, the centre of every effect's prior,
    problem.NLP_EFFECTS)."""
    from tacest.estimation.estimator import core_theta_of

    core = core_theta_of(problem, scales, estimate, "the warm estimate")
    n_eff = int(getattr(problem, "n_eff", 0))
    if not n_eff:
        return core
    eff = np.zeros(n_eff)
    if set(problem.effects) <= set(estimate.model or ()):
        from tacest.estimation.augment import effect_theta

        eff = effect_theta(problem.effects, problem.K, estimate.params, scales.L, scales.m0,
                           float(estimate.params["friction_ground"]))
    return np.concatenate([core, eff])


def _warm_theta(est, warm: Estimate) -> np.ndarray:
    """Scaled theta of a warm estimate (theta_from_estimate), its shape clipped to the
    estimator's bounds."""
    theta = theta_from_estimate(est.problem, est.scales, warm)
    ns = est.problem.n_shape
    lo, hi = est.shape.bounds(est.size_bound / est.scales.L)
    theta[:ns] = np.clip(theta[:ns], lo, hi)
    return theta


def observed_warm_runs(runs: list, fallback: list) -> list:
    """Per run, a RunEstimate whose trajectory is the run's pose observations as
    recorded (no smoothing: an impact or a bounce keeps its corner; rows not observed
    take ``fallback[i]``'s poses), velocities by differences; ``fallback[i]`` itself for
    a run without pose observations."""
    from tacest.estimation.data import pose_observation_columns

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


def _warm_z(est, runs: list, warm: Estimate, warm_runs: list) -> np.ndarray:
    """Scaled decision vector: the warm estimate's parameters and, for every run i with
    warm_runs[i] (a RunEstimate of the same length), its trajectory and impulses; the
    estimator's own start (push tracker) for the others."""
    from tacest.estimation.data import GRAVITY, touching
    from tacest.estimation.initial import initial_guess

    pr = est.problem
    theta = _warm_theta(est, warm)
    ns = pr.n_shape
    z = initial_guess(pr, runs, est.scales, theta[:ns])
    z[: pr.n_theta] = theta
    z[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(
        pr.phys_sx(theta, est.scales.L, est.scales.m0)).reshape(-1)
    L = est.scales.L
    scale = np.array([L, L, 1.0])
    for i, (run, wr) in enumerate(zip(runs, warm_runs)):
        if wr is None or np.asarray(wr.pose).shape[0] != run.n_samples:
            continue
        Lam = est.scales.m0 * GRAVITY * run.dt
        Q = (np.asarray(wr.pose, float)[:, :3] / scale).T
        Vv = (np.asarray(wr.velocity, float)[:, :3] / scale).T
        # eq. D2 holds exactly at the start, whatever dt the warm trajectory had (a
        # clock candidate changes dt; the impulse-only stage cannot move Q or V)
        Vv[:, 1:] = np.diff(Q, axis=1) / run.dt
        kw = {"Q": Q, "V": Vv}
        # impulses: written into the estimator's own start blocks, whatever their layout
        # holds (ground normal impulses first, then tangential ones when it has them)
        _, _, LG0, LF0 = pr.run_blocks(z, i)
        K = pr.K
        gn = wr.impulses.get("ground_normal")
        if gn is not None and np.asarray(gn).shape == (run.n_samples, K) and LG0.shape[0] >= K:
            LG = LG0.copy()
            LG[:K] = np.maximum(np.asarray(gn, float)[1:] / Lam, 0.0).T
            gt = wr.impulses.get("ground_tangent")
            if LG0.shape[0] >= 2 * K and gt is not None and np.asarray(gt).shape == (run.n_samples, K):
                LG[K: 2 * K] = (np.asarray(gt, float)[1:] / Lam).T
            kw["LG"] = LG
        F = run.n_fingers
        if F and all(f"finger_{f}" in wr.impulses for f in range(F)) and LF0.shape[0] == 2 * F:
            LF = np.concatenate([np.asarray(wr.impulses[f"finger_{f}"], float)[1:] for f in range(F)], axis=1)
            on = touching(run)[1:]
            LF = LF * np.repeat(on, 2, axis=1)  # off-contact finger impulses are pinned at 0
            kw["LF"] = (LF / Lam).T
        pr.set_run_blocks(z, i, **kw)
    return z


def _estimate_of(est, out, runs: list, model: list, information: bool) -> Estimate:
    """An Estimate from a LocalEstimator's solution (as estimate_runs writes it)."""
    from tacest.io.h5util import sha256_file

    V, mass, inertia, mu_g, mu_f = est.physical(out.z)[:5]
    params = {"mass": mass, "inertia": inertia, "friction_ground": mu_g, "friction_finger": mu_f}
    if model:
        from tacest.estimation.augment import effect_params

        params.update(effect_params(est.problem, out.z, est.scales.L, est.scales.m0))
    run_ests = []
    for i, run in enumerate(runs):
        pose, vel, imp = est.trajectories(out.z, i)
        res = est.per_sample_residuals(out.z, i)
        src = run.filename or ""
        run_ests.append(RunEstimate(pose=pose, velocity=vel, impulses=imp, residuals=res, source_file=src,
                                    source_sha256=sha256_file(src) if src else ""))
    info, names, std = None, [], {}
    if information:
        from tacest.information.observed import observed_information

        # the posterior's std (data and priors), as the estimator reports
        info, names, _, std = observed_information(est, out.z, posterior=True)
    return Estimate(dim=2, shape=est.shape.name, vertices=V, params=params,
                    runs=run_ests, model=list(model), solver_status=out.status, success=out.success,
                    iterations=out.iterations, wall_time=out.wall_time, objective=out.objective, information=info,
                    info_names=names, std=std, config=est.config.to_dict(), method="implicit",
                    extra_attrs={"length_scale": est.scales.L, "mass_scale": est.scales.m0})


def fit_local(runs: list, shape: str, config: EstimatorConfig, warm: Estimate = None, warm_runs: list = None,
              pinned: np.ndarray = None, pin: str = "all", echo=None, information: bool = False,
              accept_budget: bool = False, effects=(), hold_warm: bool = False) -> FitResult:
    """Fit ``runs`` with the local back end (see module docstring).

    warm : Estimate whose parameters (and, per run, ``warm_runs[i]`` trajectories) start
        the solve; without it the estimator's own cold start is used;
    pinned : scaled theta (a previous FitResult.theta) held fixed: all of it (``pin``
        "all"), its shape part only (``pin`` "shape"), or all but the shape (``pin``
        "physics": mass, inertia, frictions, effect parameters);
    accept_budget : keep the last iterate of a final stage that used up its iteration
        budget (config.solver.max_iter), reporting IPOPT's status (see BUDGET_STATUSES);
    effects : NLP augmentations (problem.NLP_EFFECTS) of the fitted model; parameters the
        warm estimate lacks start at "no effect" (see theta_from_estimate);
    hold_warm : hold every parameter (shape, mass, inertia, frictions, effect parameters)
        at the warm estimate's values: only trajectories and impulses are fitted (the
        first half of a start at a given effect strength, see typical_start_fit).
    Raises SolveFailedError when IPOPT fails.
    """
    echo = echo or _noop
    t0 = time.perf_counter()
    cls = _local_estimator_class()
    if pin not in PIN_MODES:
        raise TacestError(f"internal: pin must be one of {PIN_MODES}, got {pin!r}")
    if hold_warm and (warm is None or pinned is not None):
        raise TacestError("internal: hold_warm needs a warm estimate and no pinned theta")
    est = cls(runs, shape, config, echo, pinned_theta=pinned, pin=pin, effects=effects)
    if hold_warm:
        pinned = est.pinned_theta = _warm_theta(est, warm)
    notes = []
    warm_given = warm is not None and any(w is not None for w in (warm_runs or []))
    try:
        if warm is not None:
            z0 = _warm_z(est, runs, warm, warm_runs or [None] * len(runs))
            out = est.solve_from(_pin_start(est, z0, pinned, pin), cold=not warm_given, accept_budget=accept_budget)
        else:
            out = _cold_solve(est, runs, pinned, pin, accept_budget)
    except SolveFailedError as exc:
        if warm is None:
            raise
        # a warm start can land in a region where IPOPT stalls: try once from the
        # estimator's own consistent start (same budget), and say so
        notes.append(f"warm start failed ({exc}); solved from the estimator's start")
        echo(notes[-1])
        out = _cold_solve(est, runs, pinned, pin, accept_budget)
    if est.retried:
        notes.append("IPOPT failed to step in a final stage, which was redone once with a larger ridge")
    estimate = _estimate_of(est, out, runs, list(effects), information)
    estimate.wall_time = time.perf_counter() - t0
    theta = np.asarray(out.z[: est.problem.n_theta], float).copy()
    return FitResult(estimate=estimate, runs=list(runs), theta=theta, wall_time=estimate.wall_time, backend="local",
                     notes=notes)


def _pin_start(est, z0, pinned, pin):
    """z0 with the pinned part of theta (and the lifted quantities) set."""
    if pinned is None:
        return z0
    pr = est.problem
    if pin == "shape":
        z0[: pr.n_shape] = pinned[: pr.n_shape]
    elif pin == "physics":
        z0[pr.n_shape: pr.n_theta] = pinned[pr.n_shape:]
    else:
        z0[: pr.n_theta] = pinned
    z0[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(
        pr.phys_sx(z0[: pr.n_theta], est.scales.L, est.scales.m0)).reshape(-1)
    return z0


def _cold_solve(est, runs, pinned, pin, accept_budget):
    """The estimator's own start (start shape, push-tracker trajectories) and every
    homotopy stage; a pinned shape replaces the start shape."""
    from tacest.estimation.initial import choose_start_shape, initial_guess, start_trajectories

    pr = est.problem
    if pinned is None or pin == "physics":
        s0 = choose_start_shape(pr, runs, est.scales, est.s0)
    else:
        s0 = np.asarray(pinned[: pr.n_shape], float)
    traj = start_trajectories(pr, runs, est.scales, s0)
    z0 = initial_guess(pr, runs, est.scales, s0, traj)
    return est.solve_from(_pin_start(est, z0, pinned, pin), cold=True, accept_budget=accept_budget)


# ------------------------------------------------------------------------------------
# estimator back end


def fit_estimator(runs: list, shape: str, config: EstimatorConfig, effects=(), fixed: Estimate = None,
                  echo=None, refit_shape: bool = False) -> FitResult:
    """Fit with ``estimate_runs(..., effects=..., fixed=..., refit_shape=...)`` (the NLP
    augmentations; with ``fixed``, ``refit_shape`` holds everything but the shape).

    Raises CandidateUnavailable with a clear message when the estimator does not offer
    them (TypeError / NotImplementedError from the call)."""
    from tacest.estimation.estimator import estimate_runs

    t0 = time.perf_counter()
    kwargs = {}
    if effects:
        kwargs["effects"] = tuple(effects)
    if fixed is not None:
        kwargs["fixed"] = fixed
        if refit_shape:
            kwargs["refit_shape"] = True
    try:
        est = estimate_runs(runs, shape, config, echo=echo or _noop, method="implicit", **kwargs)
    except (TypeError, NotImplementedError) as exc:
        what = ", ".join(effects) if effects else "fixed-parameter (held-out) fits"
        raise CandidateUnavailable(f"the estimator cannot model {what} in this version "
                                   f"({exc.__class__.__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    return FitResult(estimate=est, runs=list(runs), wall_time=time.perf_counter() - t0, backend="estimator",
                     effects=tuple(effects))


def check_fit(fit: FitResult, what: str):
    if not fit.estimate.success:
        raise SolveFailedError(f"{what}: IPOPT status {fit.estimate.solver_status}")

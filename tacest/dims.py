"""The dimension registry: what tacest does for 2-D and for 3-D runs, in one place.

Every command asks this registry; none decides 2-D vs 3-D itself.  A :class:`Dimension`
names the implementations of one world dimension (simulated recording, estimation by
method, planning, exploration, diagnosis) and its shape parameterizations.  The
implementations are imported when first used, so that importing this module (and
``tacest --help``) stays cheap.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field

from tacest.errors import TacestError


def _lazy(path: str):
    """A callable that imports ``module:function`` on its first call."""
    module, name = path.split(":")

    def call(*args, **kwargs):
        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    call.__name__ = name
    call.__qualname__ = path
    return call


@dataclass(frozen=True)
class Dimension:
    """One world dimension.

    dim : 2 or 3; shapes : shape parameterizations (``K`` a vertex count); default_shape;
    methods : {estimation method: "module:function" with the signature of
    :func:`estimate_runs` less ``method``}; record, plan, explore, diagnose :
    "module:function", or None where this version has none (the command then says so)."""

    dim: int
    shapes: tuple
    default_shape: str
    methods: dict
    record: str
    plan: str = None
    explore: str = None
    diagnose: str = None
    notes: dict = field(default_factory=dict)

    def implementation(self, what: str):
        """The callable doing ``what`` (record, plan, explore, diagnose) in this dimension;
        a TacestError (one line) where there is none."""
        path = getattr(self, what)
        if path is None:
            raise TacestError(f"{what} is not available for {self.dim}-D runs in this version"
                              + (f" ({self.notes[what]})" if what in self.notes else ""))
        return _lazy(path)

    def estimator(self, method: str):
        if method not in self.methods:
            raise TacestError(f"method {method!r} is not available for {self.dim}-D runs; "
                              f"use {' or '.join(self.methods)}")
        return _lazy(self.methods[method])


DIMENSIONS = {
    2: Dimension(dim=2, shapes=("box", "polygon:K"), default_shape="box",
                 methods={"implicit": "tacest.estimation.estimator:estimate_2d",
                          "shooting": "tacest.estimation.shooting:estimate_shooting"},
                 record="tacest.sim.record:record_sim", plan="tacest.planning.planner:plan_next",
                 explore="tacest.planning.explore:explore", diagnose="tacest.diagnosis.diagnose:diagnose"),
    3: Dimension(dim=3, shapes=("box", "polytope:K"), default_shape="box",
                 methods={"implicit": "tacest.estimation.estimator3d:estimate_3d"},
                 record="tacest.sim3d.record:record_sim", plan="tacest.planning.planner:plan_next",
                 explore="tacest.planning.explore:explore", diagnose="tacest.diagnosis.diagnose3d:diagnose_3d"),
}


def dimension(dim) -> Dimension:
    """The registry entry of ``dim``; a TacestError for another value."""
    try:
        return DIMENSIONS[int(dim)]
    except (KeyError, TypeError, ValueError):
        raise TacestError(f"dimension must be 2 or 3, got {dim!r}") from None


def dimension_of(runs) -> Dimension:
    """The one dimension of a list of runs; a TacestError for none or a mix."""
    if not runs:
        raise TacestError("no run files given")
    dims = {int(r.dim) for r in runs}
    if len(dims) > 1:
        raise TacestError("runs mix 2-D and 3-D recordings; use them separately")
    return dimension(dims.pop())


def estimate_runs(runs, shape_spec: str = "box", config=None, method: str = "implicit", effects=(), fixed=None,
                  refit_shape: bool = False, previous=None):
    """Estimate one object from its runs (all of one dimension): the dimension's
    estimator for ``method``.  effects, fixed, refit_shape : see
    tacest.estimation.estimator.estimate_2d (fixed and refit_shape: the 2-D implicit
    estimator only; effects: the implicit estimators of both dimensions); previous : an
    earlier Estimate of the first samples of the same runs, one more start (the
    implicit estimators: tacest.estimation.estimator.previous_start_2d,
    tacest.estimation.estimator3d.previous_start)."""
    dim = dimension_of(runs)
    if method not in ("implicit", "shooting"):
        raise TacestError(f"unknown method {method!r}: use implicit or shooting")
    if fixed is not None and not (dim.dim == 2 and method == "implicit"):
        raise TacestError("fixed= is offered by the implicit 2-D estimator only")
    if tuple(effects or ()) and method != "implicit":
        raise TacestError("effects= are offered by the implicit estimators only")
    if previous is not None and method != "implicit":
        raise TacestError("starting from an earlier estimate is offered by the implicit estimators only")
    if method == "implicit" and fixed is None:
        from tacest.estimation.config import EstimatorConfig
        from tacest.io.resample import coarsening_factor

        config = config or EstimatorConfig()
        ks = [coarsening_factor(r.dt, config.solver.sample_period) for r in runs]
        if max(ks) > 1:
            return _estimate_coarsened(runs, ks, shape_spec, config, effects, previous)
    kwargs = {}
    if previous is not None:
        kwargs["previous"] = previous
    if effects:
        kwargs["effects"] = tuple(effects)
    if fixed is not None:
        kwargs.update(fixed=fixed, refit_shape=refit_shape)
    return dim.estimator(method)(runs, shape_spec, config, **kwargs)


def _estimate_coarsened(runs, ks, shape_spec, config, effects, previous):
    """estimate_runs on runs sampled faster than solver.sample_period: each run i fitted
    at ks[i] times its period, the estimate's trajectories brought back to every sample
    (tacest.io.resample); its attr ``fitted_every`` lists ks."""
    import dataclasses
    import json
    import logging

    from tacest.io.resample import coarsen_run, coarsen_run_estimate, refine_run_estimate

    logging.getLogger(__name__).info(
        "fitting " + ", ".join(f"run {i} ({r.dt * 1e3:.3g} ms) every {k} samples" for i, (r, k) in
                               enumerate(zip(runs, ks)) if k > 1) + " (solver.sample_period; docs/estimation.md)")
    coarse = [coarsen_run(r, k) for r, k in zip(runs, ks)]
    if previous is not None and len(previous.runs) == len(runs):
        previous = dataclasses.replace(previous, runs=[coarsen_run_estimate(re, k)
                                                       for re, k in zip(previous.runs, ks)])
    est = estimate_runs(coarse, shape_spec, dataclasses.replace(config, solver=dataclasses.replace(
        config.solver, sample_period=0.0)), "implicit", effects=effects, previous=previous)
    est.runs = [refine_run_estimate(re, r, k) for re, r, k in zip(est.runs, runs, ks)]
    est.extra_attrs["fitted_every"] = json.dumps([int(k) for k in ks])
    if est.fit_quality:  # its windows in the run's own samples (coarse sample j stands at sample j·k)
        q = est.fit_quality
        for w in q.get("worst", []):
            k = ks[int(w["run"])]
            w["start"], w["stop"] = int(w["start"]) * k, min(int(w["stop"]) * k, runs[int(w["run"])].n_samples)
        n_full, n_coarse = sum(r.n_samples for r in runs), max(int(q.get("n_samples", 0)), 1)
        q["flagged_samples"] = int(round(int(q.get("flagged_samples", 0)) * n_full / n_coarse))
        q["n_samples"] = int(n_full)
    est.config["solver"]["sample_period"] = config.solver.sample_period  # as given (the inner fit's: 0)
    return est


def record_sim(opts, **kwargs):
    """A simulated recording in the world of ``opts.dim`` (tacest.sim.record.SimOptions)."""
    opts.validate()
    return dimension(opts.dim).implementation("record")(opts, **kwargs)

"""One estimate assembly for every estimator (2-D, 3-D, shooting, diagnosis fits): the
parameters, trajectories and solver outcome as a tacest.io.estimate.Estimate, with one
policy for what is reported as identifiable and which std is written.

Policy (:func:`identifiability`), in this order:

1. what the sensors cannot tell: mass and inertia without a force stream (every impulse
   scales with the mass; DESIGN), finger friction without a fingertip;
2. what the data leave (nearly) undetermined: mass and the frictions whose data std
   (tacest.estimation.uncertainty.Information.std_data) exceeds half their value;
3. what ended at its hard bound (the bound holds it, not the data);
4. what a penalty term put where it is (2-D pose-observed fits: the data alone would
   move it by more than OCCAM_SHIFT_SIGMAS of its std);
5. effect parameters: identifiable where the data's std is finite and below the
   effect's prior sigma (the data tell more than the prior);
6. force_scale's gain and the mass: only their product is identifiable;
7. a fit with every parameter held: nothing was estimated.

The ``std`` written is the posterior's (data and priors): what a user reads as the
uncertainty of an estimate.  Whether the data determine a parameter is item 2 above.
Where another start's fit lies within the likelihood-ratio bound of the kept one
(:func:`basin_spread`), the data cannot tell the two basins apart: the std of the shape,
mass and frictions is widened by the distance between them, in quadrature.

``std["shape"]`` (m) is the shape's in one number: the RMS over the vertices of their
one-sigma position uncertainty in the body frame (uncertainty.shape_std), combined in
quadrature with the contact model's tolerance ``noise.contact_gap`` (0.5 mm): the smooth
contact terms place a surface within about that of where a hard contact would, however
many samples touch it (a bias, not noise: more data do not shrink it).

Every estimate carries its goodness-of-fit test (tacest.estimation.fitquality): a fit
whose residuals exceed the stated noise floor is marked inconsistent (a warning says
where), and its std is widened by the excess it shows there (the square root of the
flagged windows' ‖r‖² per degree of freedom: the noise level those data show, as if it
held everywhere; ``std_scale`` in its fit_quality).  The widened std is no calibrated
error bar either: the mark says so.  A local misfit (a few samples at an instant the
model simplifies) is consistent, and its std is widened the same way.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from tacest.estimation.fitquality import goodness_of_fit
from tacest.estimation.sensor_noise import rejudged
from tacest.estimation.solver import SolveOutcome, attempts_json
from tacest.estimation.uncertainty import Information, shape_std
from tacest.io.estimate import Estimate

log = logging.getLogger(__name__)

#: distance (log mass, or friction) from a bound within which a fitted parameter counts
#: as ended at that bound (IPOPT's interior point stops within ~1e-8 of an active bound)
AT_BOUND_TOLERANCE = 1e-3
#: a mass or friction whose first-order shift without the Occam term (the data alone)
#: exceeds this many of its std is reported as not identifiable: at 2 the data's own
#: optimum lies outside the value's 95 % interval
OCCAM_SHIFT_SIGMAS = 2.0
#: a mass or friction whose data std exceeds this fraction of its value is reported as
#: not identifiable: one sigma reaches half the value
UNDETERMINED_FRACTION = 0.5


@dataclass
class FitFacts:
    """What the identifiability policy needs besides the parameters and the information.

    has_force : a fingertip's force was measured while it touched (data.force_in_contact:
    what tells the mass); has_fingers : a fingertip touched;
    at_bound : {name: True} for parameters that ended at a hard bound; effect_sigma :
    {information row name: prior sigma in physical units} of the effect parameters;
    effects : the modelled effects' names; held : every parameter was held fixed;
    shape_seen : some fingertip touched (a contact flag 1) or some pose was observed;
    shape_names : the information rows of the shape's parameters; shape_at_bound : the
    shape parameters that ended at a hard bound (:func:`shape_params_at_bound`)."""

    has_force: bool
    has_fingers: bool
    at_bound: dict = field(default_factory=dict)
    effect_sigma: dict = field(default_factory=dict)
    effects: tuple = ()
    held: bool = False
    shape_seen: bool = True
    shape_names: tuple = ()
    shape_at_bound: tuple = ()


def shape_seen(runs: list) -> bool:
    """Whether the runs measure the shape at all: some fingertip touched (a contact
    flag 1 that arrived) or some pose was observed.  Without either nothing tells the
    object's extent (a run in which no fingertip touched)."""
    for r in runs:
        if r.contact is not None and r.n_fingers and np.any(r.contact.astype(bool) & ~r.finger_missing_mask):
            return True
        if r.pose_obs is not None and np.any(np.all(np.isfinite(r.pose_obs), axis=1)):
            return True
    return False


def ended_at_bound(u: float, bounds) -> bool:
    """Whether a scaled value u sits within AT_BOUND_TOLERANCE of either of its bounds."""
    return not bounds[0] + AT_BOUND_TOLERANCE < u < bounds[1] - AT_BOUND_TOLERANCE


def shape_params_at_bound(shape, s, size_bound_scaled: float, names=None) -> tuple:
    """Names ("<parameter> (lower|upper)", ``names`` or the shape's param_names) of the
    shape parameters s (scaled, units of the length scale L) that ended within
    AT_BOUND_TOLERANCE of their hard bounds ``shape.bounds(size_bound_scaled)`` (2-D or
    3-D Shape): a box extent at the smallest size allowed (5 % of the size bound) or at
    the size bound itself."""
    lo, hi = (np.asarray(b, float) for b in shape.bounds(size_bound_scaled))
    s = np.asarray(s, float).reshape(-1)[: len(lo)]
    names = list(names or getattr(shape, "param_names", None) or []) or [f"s{k}" for k in range(len(lo))]
    return tuple(f"{n} ({'lower' if u - a < b - u else 'upper'})"
                  for n, u, a, b in zip(names, s, lo, hi) if ended_at_bound(u, (a, b)))


def implausible_friction(params: dict, prior: dict) -> list:
    """The friction coefficients of ``params`` outside the plausible range
    ``prior["friction_plausible"]`` ([low, high]; absent: config.Prior's default), as
    "friction_ground 1.97 > 1.8".  Each of the 11 fits of the 2-D benchmarks (120
    recordings) that ended outside that range was in a wrong basin, 2.9-31 mm off: a
    light and grippy object (ground friction 1.8-2.0, the upper bound) or a wrong shape
    that drifts on a frictionless fingertip (0.010-0.019); the right fits stayed within
    0.04-1.3 (docs/estimation.md, "Goodness of fit")."""
    from tacest.estimation.config import Prior

    lo, hi = (float(x) for x in prior.get("friction_plausible", Prior.friction_plausible))
    out = []
    for k in ("friction_ground", "friction_finger"):
        v = float(params.get(k, np.nan))
        if v < lo:
            out.append(f"{k} {v:.3g} < {lo:g}")
        elif v > hi:
            out.append(f"{k} {v:.3g} > {hi:g}")
    return out


def start_verdict(est, out, saved) -> tuple:
    """What solver.solve_from_starts' ``solve_one`` returns for the fit ``out`` of the
    estimator ``est`` (2-D or 3-D: its physical, physics_per_sample and fit_quality at
    out.z): (out, physics per sample, saved, may_be_right, found).  ``may_be_right``:
    its data misfit is at most local (FitQuality.local) and its friction plausible
    (:func:`implausible_friction`, listed in ``found["implausible"]`` where it is not):
    a fit that is not is a wrong basin worth another start."""
    V, mass, _, mu_g, mu_f = est.physical(out.z)
    params = {"mass": float(mass), "friction_ground": float(mu_g), "friction_finger": float(mu_f)}
    found = {"vertices": np.asarray(V, float), "params": params}
    odd = implausible_friction(params, est.config.to_dict().get("prior", {}))
    if odd:
        found["implausible"] = odd
    local = est.fit_quality(out.z).local  # None: not tested
    return out, est.physics_per_sample(out.z), saved, False if odd else local, found


def identifiability(params: dict, info: Optional[Information], facts: FitFacts) -> dict:
    """{name: bool} by the module's policy; warnings (logging) say why a parameter that
    the sensors could tell is not identifiable."""
    ident = {"mass": facts.has_force, "inertia": facts.has_force, "friction_ground": True,
             "friction_finger": facts.has_fingers}
    std = info.std_data if info is not None else {}
    for k in ("friction_ground", "friction_finger", "mass"):
        if k in std and not std[k] <= UNDETERMINED_FRACTION * max(float(params[k]), 1e-3):
            ident[k] = False
    for k, hit in facts.at_bound.items():
        if hit and ident.get(k) and not facts.held:
            ident[k] = False
            log.warning(f"{k} = {float(params[k]):.4g} ended at its bound: the data do not determine it")
    shift = info.shift if info is not None else {}
    for k in ("mass", "friction_ground", "friction_finger"):
        if ident.get(k) and abs(shift.get(k, 0.0)) > OCCAM_SHIFT_SIGMAS * std.get(k, np.inf):
            ident[k] = False
            log.warning(f"{k} = {float(params[k]):.4g} is set by the Occam term, not the data (without it the "
                        f"data would move it by {shift[k]:+.3g}, std {std[k]:.3g})")
    for k, sigma in facts.effect_sigma.items():
        ident[k] = bool(np.isfinite(std.get(k, np.inf)) and std.get(k, np.inf) < sigma)
    if "force_scale" in facts.effects:
        # every force in the model (weight, inertia, contacts) scales with the mass, the
        # measured ones with the gain: only gain × mass is identifiable (docs/diagnosis.md)
        ident["mass"] = ident["force_scale.gain"] = False
    ident["shape"] = bool(facts.shape_seen and all(np.isfinite(std.get(k, 0.0)) for k in facts.shape_names))
    if not facts.shape_seen and not facts.held:
        log.warning("no fingertip touched the object and no pose was observed: the shape is the estimator's "
                    "starting guess, not an estimate (identifiable shape: false)")
    if facts.held:
        ident = {k: False for k in ident}
    return ident


#: confidence of the likelihood-ratio region within which another basin's fit counts
#: as plausible (basin_spread)
BASIN_CONFIDENCE = 0.95


def not_converged_note(est) -> Optional[str]:
    """The one line that tells a user an estimate is IPOPT's last iterate of a final
    stage that used up its budget (kept as the fit of lowest objective among the starts:
    solver.solve_from_starts), or None for a converged one (or a planner's start guess)."""
    if est.success or est.solver_status == "start guess":
        return None
    return (f"IPOPT did not converge ({est.solver_status}, {est.iterations} iterations): the estimate is the last "
            "iterate of its final stage, kept as the fit of lowest objective among the starts (attr starts); its "
            "stds come from a point that is not stationary")


def basin_spread(attempts: list, objective: float, vertices, params: dict) -> dict:
    """{name: how far another plausible basin's fit lies from the kept one}: "shape" (m,
    the Chamfer distance of the two shapes after the best rigid alignment) and mass,
    friction_ground, friction_finger (their differences), maximized over the other
    fits of the estimate's starts (those that used up their iteration budget included) whose objective is within half the
    BASIN_CONFIDENCE quantile of χ²(p) of the kept one's, p the number of compared
    parameters (shape parameters as vertices' coordinates, and the three): the fits a
    likelihood-ratio test cannot tell from the kept one.  A local Laplace std says
    nothing about another basin; the reported std is widened by this spread in
    quadrature.  {} when there is none."""
    from scipy.special import chdtri  # chi2.ppf(q, k) = chdtri(k, 1 - q), without scipy.stats' import

    from tacest.geometry.chamfer import chamfer_body

    V = np.asarray(vertices, float)
    limit = 0.5 * float(chdtri(V.size + 3, 1.0 - BASIN_CONFIDENCE))
    out = {}
    for a in attempts:
        if "vertices" not in a or not np.isfinite(a.get("objective", np.inf)):
            continue
        if a["objective"] > objective + limit:
            continue
        Va = np.asarray(a["vertices"], float)
        if Va.shape != V.shape or np.array_equal(Va, V):
            continue
        d = {"shape": float(chamfer_body(Va, V))}
        d.update({k: abs(float(v) - float(params[k])) for k, v in a.get("params", {}).items() if k in params})
        for k, v in d.items():
            out[k] = max(out.get(k, 0.0), v)
    if out:
        log.info("another start's fit is within the likelihood-ratio bound of the kept one: the std covers the "
                 "spread between them (" + ", ".join(f"{k} {v:.3g}" for k, v in out.items()) + ")")
    return out


def assemble(dim: int, shape: str, vertices, params: dict, runs: list, outcome: SolveOutcome, wall_time: float,
             info: Optional[Information], facts: FitFacts, config: dict, method: str, extra: dict = None,
             attempts: list = None, notes: list = (), data: list = None, vertex_jacobian=None,
             sensor_noise: dict = None) -> Estimate:
    """The Estimate of a fit (see the module docstring); ``data``: the runs fitted (for
    the goodness-of-fit test; without them the estimate is untested); vertex_jacobian
    (K·dim, n_shape): the vertices' derivative by the shape parameters, the first
    n_shape rows of the information (for std["shape"], uncertainty.shape_std);
    sensor_noise: the report of tacest.estimation.sensor_noise.noise_report (attr
    ``sensor_noise``, JSON): streams noisier than configured are judged by the test at
    their measured level (the information ``info`` already weighs them so:
    sensor_noise.judged_params)."""
    quality = None
    std = {} if info is None else dict(info.std)
    if info is not None and info.cov is not None and vertex_jacobian is not None:
        ns = np.asarray(vertex_jacobian).shape[1]
        floor = float((config or {}).get("noise", {}).get("contact_gap", 0.0))
        std["shape"] = float(np.hypot(shape_std(vertex_jacobian, info.cov[:ns, :ns], dim), floor))
    spread = basin_spread(attempts or [], outcome.objective, vertices, params)
    for k, d in spread.items():
        if k in std and d > 0:
            std[k] = float(np.hypot(std[k], d))
    if data is not None:
        weights = (config or {}).get("weights", {})
        q = goodness_of_fit(rejudged([r.residuals for r in runs], sensor_noise or {}), data,
                            len(np.asarray(vertices)), weights=weights)
        quality = q.to_json()
        if facts.shape_at_bound and not facts.held:
            # not an interior optimum: the bound, not the data, holds the shape, and a
            # Laplace std says nothing there (docs/estimation.md, "Goodness of fit")
            quality["consistent"] = False
            quality["shape_at_bound"] = list(facts.shape_at_bound)
        odd = [] if facts.held else implausible_friction(params, (config or {}).get("prior", {}))
        if odd:  # the signature of a wrong basin (docs/estimation.md, "Goodness of fit")
            quality["consistent"] = False
            quality["implausible"] = odd
        scale = 1.0
        if q.worst:  # inconsistent, or a local misfit (consistent; its std widened all the same)
            # only for the debug log here: a diagnosis fits models that misfit on
            # purpose; the commands that hand this estimate to a user say it once
            # (cli/logs.py, warn_fit_quality)
            log.debug(q.summary())
            scale = q.std_scale
            std = {k: v * scale for k, v in std.items()}
        quality["std_scale"] = scale
    extra = dict(extra or {})
    extra["stages"] = "; ".join(f"{s.name}: {s.status} ({s.iterations} it, {s.wall_time:.2f} s)"
                                for s in outcome.stages)
    if attempts:
        extra["starts"] = attempts_json(attempts)
    if notes:
        extra["notes"] = "; ".join(notes)
    if sensor_noise:
        extra["sensor_noise"] = json.dumps(sensor_noise)
    return Estimate(
        dim=dim, shape=shape, vertices=np.asarray(vertices, float), params=params, runs=runs,
        model=list(facts.effects), solver_status=outcome.status, success=outcome.success,
        iterations=outcome.iterations, wall_time=wall_time, objective=outcome.objective,
        information=None if info is None else info.matrix, info_names=[] if info is None else list(info.names),
        std=std, identifiable=identifiability(params, info, facts),
        config=config, method=method, extra_attrs=extra, fit_quality=quality)

"""The experiment that decides: the pokes whose predicted measurements differ most between
the leading candidate models of a diagnosis (2-D, and 3-D in the MuJoCo world).

A diagnosis ends with a ranking of candidate effects; when the held-out data cannot tell
the leaders apart (or show no effect at all), what to record next is the action under
which their predictions differ most relative to the sensor noise.  For Gaussian sensor
noise the expected log-likelihood ratio of model A against model B on the data of an
action, when A is true, is

    E_A[log p_A(m) - log p_B(m)] = 0.5 Σ_t |(m_A(t) - m_B(t)) / σ|²,

the same in both directions: the expected discrimination :func:`discrimination`.  Its
predictions m_A, m_B come from the same forward model as planning (the pymunk world of
tacest.information.expected.predict_poke; in 3-D the MuJoCo world of
tacest.information.expected3d.predict_poke_3d; the estimate's object at its last pose), with
each candidate's fitted effect in the world (restitution, drag, damping, soft ground, COM
offset) or on the sensor (force bias and gain, latency: tacest.sim.record.sensor_streams,
noiseless).  Terms, per sample and finger: the force at every sample (a clean sensor reads
0 off contact, a biased one its bias), the contact normal where both models touch, a
contact flag that one model sets and the other not (CONTACT_FLIP_LLR), and the pose where
the runs observe it.

Two criteria, by what the diagnosis found:

- **separate** (the diagnosis blamed an effect, or could not decide): the models
  compared are the plain model (``none``) and the ``leaders - 1`` best candidates whose
  fit succeeded, with their fitted parameters; an action scores log(1 + the smallest
  pairwise discrimination), so that the chosen action separates every pair.
- **screen** (verdict ``none``: the data show no effect yet).  The candidates' fitted
  parameters are then what the noise made of them, and their ranking too: aiming at the
  best two of them aims at noise (docs/diagnosis.md, "Touch alone").  The question is
  which experiment would show an effect if one is there, so every candidate the
  diagnosis compared and a prediction can use is drawn SCREEN_DRAWS times from its
  typical range (the simulator's random draws, tacest.sim.effects, for the estimated
  object: drag m/τ, damping I/τ, a COM 0.25-0.45 inradius off, ...; face_friction too,
  whose draws give every face its coefficient), and an action scores the mean over
  candidates and draws of log(1 + min(D, SCREEN_DETECT)), D its discrimination from the
  plain model: an effect counts once it would be seen, so an action that shows every
  effect beats one that shows a few hugely; among actions that show every draw, the
  one whose weakest draw shows most (SCREEN_TIE_WEIGHT).  force_scale is left out
  unless the mass is known (without it a gain is a mass: no action shows it).

The search is the planner's (cross-entropy method over the planner's action space,
tacest.planning.actions, ``--poke-style``); the N best distinct actions are written as
plan files (SPEC ``tacest.plan``: ``method`` ``discriminate``, ``score``
``expected_llr``), each executable with ``tacest record --plan``.

Not modelled by the predictions: ``time_scale`` (a clock error changes the time stamps,
not what one poke measures against another), ``face_friction`` with its fitted values
(its per-face values are not kept in the diagnosis' candidate parameters; screening
draws them) and tacest's 3-D extensions ``edge_radius`` and ``ground_offset`` (the
simulator has no such effect); a candidate of these is left out and said so.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from tacest.errors import TacestError

log = logging.getLogger(__name__)

#: per-sample probability that a tactile contact flag is wrong: a sample where one model
#: predicts a touch and the other does not is worth log((1 - ε) / ε) nats of
#: discrimination (ε = 0.01: about 4.6 nats per sample)
CONTACT_FLIP_RATE = 0.01
CONTACT_FLIP_LLR = math.log((1 - CONTACT_FLIP_RATE) / CONTACT_FLIP_RATE)
#: effects whose candidate parameters a prediction can use (module docstring)
PREDICTABLE = ("restitution", "angular_damping", "linear_drag", "soft_contact", "force_bias", "force_scale",
               "latency", "com_offset")
#: default number of models compared: the plain model and the best two candidates
LEADERS = 3
#: effects a screening prediction can draw (PREDICTABLE, and face_friction: its drawn
#: per-face values act in the simulated world)
SCREENABLE = PREDICTABLE + ("face_friction",)
#: random draws of each candidate effect from its typical range when screening (module
#: docstring): two, so that a signed effect (a force bias, a COM offset) is seen in two
#: directions at the cost of 2 predictions per candidate and action
SCREEN_DRAWS = 2
#: nats: the discrimination at which screening counts an effect as shown (module
#: docstring).  The diagnosis blames an effect whose held-out improvement exceeds its
#: penalty, 0.5 ln N per parameter (3.5-4.5 nats over 1000-8000 held-out samples), by a
#: real share of the gap; about two to three penalties of expected log-likelihood ratio
#: is what it can see.  Beyond it a larger D adds no detection, and without the cap the
#: mean of logs was led by effects already shown a million times over (a bounce, a
#: latency: 1e5-1e7 nats on a dynamic poke) while a drag showed 0.003
SCREEN_DETECT = 10.0
#: weight of log(1 + the smallest discrimination over candidates and draws) added to a
#: screening score: it only orders actions whose capped scores tie (on the touch-alone
#: loops 4-6 of the 36 searched pokes had every drawn effect above SCREEN_DETECT, and the
#: first of them was kept); 1e-6 × log(1 + 1e7) = 1.6e-5, below any real difference
SCREEN_TIE_WEIGHT = 1e-6
#: the criteria (module docstring)
SEPARATE, SCREEN = "separate", "screen"


@dataclass
class Suggestion:
    """A suggested experiment: ``plan`` (tacest.io.plan.Plan, chosen action and the
    searched candidates with their scores), ``models`` compared, ``pairwise``
    {"A vs B": expected discrimination (nats) of the chosen action; screening: its mean
    over B's draws}, ``criterion`` SEPARATE or SCREEN (module docstring)."""

    plan: object
    models: list
    pairwise: dict = field(default_factory=dict)
    criterion: str = SEPARATE


def sim_effects_of(name: str, params: dict, dim: int = 2) -> list:
    """The resolved simulator effects (tacest.sim.effects.Effect) of a candidate with its
    fitted parameters (/params names ``effect.parameter``, or the transform's parameter
    name) in a ``dim``-D world; [] for ``none``; TacestError for an effect a prediction
    cannot use."""
    from tacest.sim.effects import EFFECTS, NONE, Effect

    if name == NONE:
        return []
    if name not in PREDICTABLE:
        raise TacestError(f"{name}: its fitted model cannot be predicted (tacest.diagnosis.suggest)")
    values = {k.split(".", 1)[1] if k.startswith(name + ".") else k: v for k, v in params.items()}
    if name == "soft_contact" and "damping" not in values and values.get("stiffness") is not None:
        # the 3-D model's ground sinks quasi-statically (no damper fitted): the simulator's
        # plate damped critically, the quickest settling a damper gives
        from tacest.sim3d.world import SOFT_PLATE_MASS

        values["damping"] = 2.0 * math.sqrt(float(values["stiffness"]) * SOFT_PLATE_MASS)
    out = {}
    for p in EFFECTS[name].param_names:
        if p in ("fz", "dz") and dim == 2:  # 3-D only
            continue
        v = values.get(p)
        if v is None or not np.isfinite(float(v)):
            raise TacestError(f"{name}: fitted parameter {p} is missing")
        out[p] = int(round(float(v))) if p == "samples" else float(v)
    return [Effect(name=name, params=out)]


def predicted_measurements(model, action, effects, has_pose: bool) -> dict:
    """Noiseless measurements of one poke on ``model`` (ModelState, or ModelState3 in the
    MuJoCo world) with ``effects``: {contact (T, F) bool, force (T, F, D) N, normal
    (T, F, D), pose (T, 3) [x, y, angle] or (T, 7) [p, q], or None}."""
    from tacest.information.expected import predict_poke
    from tacest.information.expected3d import ModelState3, predict_poke_3d
    from tacest.sim.record import sensor_streams

    predict = predict_poke_3d if isinstance(model, ModelState3) else predict_poke
    pred = predict(model, action, effects=effects)
    contact, force, normal = sensor_streams(pred.contact, pred.impulse__world, pred.normal__world, pred.dt,
                                            effects, 0.0, 0.0, np.random.default_rng(0))
    return {"contact": contact.astype(bool), "force": force, "normal": normal,
            "pose": pred.pose if has_pose else None}


def discrimination(a: dict, b: dict, noise: dict) -> float:
    """Expected log-likelihood ratio (nats) between two predictions (module docstring);
    noise : {force N, normal rad, position m, angle rad}."""
    T = min(a["contact"].shape[0], b["contact"].shape[0])
    ca_, cb = a["contact"][:T], b["contact"][:T]
    total = float(np.sum(ca_ != cb)) * CONTACT_FLIP_LLR
    if noise.get("force") is not None:
        total += 0.5 * float(np.sum(((a["force"][:T] - b["force"][:T]) / noise["force"]) ** 2))
    both = ca_ & cb
    dn = np.where(both[..., None], np.nan_to_num(a["normal"][:T]) - np.nan_to_num(b["normal"][:T]), 0.0)
    total += 0.5 * float(np.sum((dn / noise["normal"]) ** 2))
    if a["pose"] is not None and b["pose"] is not None:
        pa, pb = a["pose"][:T], b["pose"][:T]
        D = 2 if pa.shape[1] == 3 else 3
        if D == 2:
            angle = pa[:, 2] - pb[:, 2]
        else:  # the rotation between the two orientations
            angle = 2 * np.arccos(np.clip(np.abs(np.sum(pa[:, 3:] * pb[:, 3:], axis=1)), 0.0, 1.0))
        total += 0.5 * float(np.sum(((pa[:, :D] - pb[:, :D]) / noise["position"]) ** 2)
                             + np.sum((angle / noise["angle"]) ** 2))
    return total


def ranked_candidates(diag) -> list:
    """[(name, fitted parameters)] of a diagnosis' candidates whose fits succeeded, best
    first (2-D: tacest.diagnosis.diagnose.Diagnosis; 3-D: diagnose3d.Diagnosis3D).  In
    2-D the held-out candidates come first, in the diagnosis' order, then those not held
    out because their fit to all data improved by less than their penalty
    (diagnose.screened_for_fit), most improving first: where the data cannot tell the
    candidates apart, those are the ones an experiment must."""
    if hasattr(diag, "fits"):  # 3-D
        return [(e["name"], diag.fits[e["name"]].params) for e in diag.effects]
    from tacest.diagnosis.diagnose import screened_for_fit

    below = sorted((c for c in diag.effects if screened_for_fit(c)), key=lambda c: -c.full_improvement)
    return [(c.name, c.params) for c in diag.effects if c.status == "ok"] + [(c.name, c.params) for c in below]


def leading_models(diag, leaders: int = LEADERS, dim: int = 2) -> tuple:
    """([(name, sim effects)] of the plain model and the best candidates a prediction can
    use, in the diagnosis' order; [(name, why)] of the candidates left out)."""
    models, skipped = [("none", [])], []
    for name, params in ranked_candidates(diag):
        if len(models) >= leaders:
            break
        try:
            models.append((name, sim_effects_of(name, params, dim)))
        except TacestError as exc:
            skipped.append((name, str(exc)))
    return models, skipped


def model_of(diag, runs: list, config=None):
    """The planning model state (ModelState, 3-D ModelState3) of a diagnosis' plain
    estimate ``diag.base`` at the end of its runs ``runs``; config : EstimatorConfig of
    the 3-D diagnosis (None: the defaults)."""
    if int(runs[-1].dim) == 3:
        from tacest.estimation.config import EstimatorConfig
        from tacest.information.expected3d import ModelState3

        return ModelState3.from_estimate(diag.base, runs, config or EstimatorConfig())
    from tacest.information.expected import ModelState

    return ModelState.from_estimate(diag.base, runs)


def criterion_for(diag) -> str:
    """SCREEN when the diagnosis' verdict is ``none`` (no effect shown yet), else SEPARATE
    (module docstring)."""
    from tacest.sim.effects import NONE

    return SCREEN if getattr(diag, "verdict", None) == NONE else SEPARATE


def compared_names(diag) -> list:
    """Names of the candidates a diagnosis compared or could have (2-D: every candidate
    but those unavailable for its data; 3-D: those it fitted), in its order."""
    if hasattr(diag, "fits"):  # 3-D
        return [e["name"] for e in diag.effects]
    return [c.name for c in diag.effects if c.status != "unavailable"]


def screening_models(diag, model, dim: int, seed: int = 0, draws: int = SCREEN_DRAWS, config=None) -> tuple:
    """([(name, [[effect of draw 1], [effect of draw 2], ...])] of the plain model (one
    empty set) and of every screenable candidate the diagnosis compared, each drawn
    ``draws`` times from its typical range for the estimated object ``model`` (module
    docstring); [(name, why)] of those left out).  Seeded: the same ``seed`` draws the
    same effects.  3-D: whether the mass is known comes from ``config`` (the
    diagnosis' EstimatorConfig)."""
    from tacest.diagnosis.diagnose import EQUIVALENT_TO_PLAIN, mass_is_known
    from tacest.estimation.config import EstimatorConfig
    from tacest.sim.effects import resolve_effect

    if dim == 3:
        from tacest.sim3d.record import effect_context
    else:
        from tacest.sim.record import effect_context
    ctx = effect_context(model.sim_object())
    prior = getattr(diag, "mass_prior", None)
    mass_known = bool(prior.get("known")) if prior else mass_is_known(config or EstimatorConfig())
    models, skipped = [("none", [[]])], []
    for name in compared_names(diag):
        if name not in SCREENABLE:
            skipped.append((name, "its effect cannot be predicted (tacest.diagnosis.suggest)"))
        elif name in EQUIVALENT_TO_PLAIN and not mass_known:
            skipped.append((name, "without a known mass it is a mass: no action shows it"))
        else:
            rng = np.random.default_rng(np.random.SeedSequence([int(seed), 43, SCREENABLE.index(name)]))
            models.append((name, [[resolve_effect(name, {}, rng, ctx)] for _ in range(int(draws))]))
    return models, skipped


def _noise(diag, last) -> dict:
    """The sensor noise a discrimination is measured against (the run's, else the
    estimate's configuration): {force N or None, normal rad, position m, angle rad}."""
    cfg_noise = diag.base.config.get("noise", {}) if isinstance(diag.base.config, dict) else {}
    noise = {"force": float(last.extra_attrs.get("noise_force", cfg_noise.get("force", 0.05))) if last.has_force
             else None,
             "normal": float(last.extra_attrs.get("noise_normal", cfg_noise.get("normal", 0.05))),
             "position": float(last.sigma_position) if last.has_pose_obs else 1.0,
             "angle": float(last.sigma_angle) if last.has_pose_obs else 1.0}
    for k in ("force", "normal"):
        if noise[k] is not None:
            noise[k] = max(noise[k], 1e-3)  # a noiseless recording still has a resolution
    return noise


def suggest(diag, runs: list, n: int = 1, leaders: int = LEADERS, poke_style: str = "dynamic", seed: int = 0,
            iterations: int = 3, population: int = 12, config=None, criterion: str = None) -> list:
    """The ``n`` best distinct pokes to tell the diagnosis' models apart (module
    docstring): a list of :class:`Suggestion`, best first.  runs : the runs of
    ``diag.base`` (the plain model's estimate: the object's state and fingers at the end
    of the last one; 3-D: the held-out runs, ``diag.base_runs``); config : the
    diagnosis' EstimatorConfig (3-D; None: the defaults); criterion : SEPARATE or SCREEN
    (None: criterion_for(diag))."""
    from tacest.io.plan import Plan
    from tacest.planning.actions import action_space_for
    from tacest.parallel import forked_map
    from tacest.planning.cem import cem_maximize

    if n < 1:
        raise TacestError("--suggest needs N >= 1")
    dim = int(runs[-1].dim)
    if not runs[-1].n_fingers:
        raise TacestError("--suggest: the runs have no fingertip to poke with")
    criterion = criterion or criterion_for(diag)
    if criterion not in (SEPARATE, SCREEN):
        raise TacestError(f"unknown suggestion criterion {criterion!r}: use {SEPARATE} or {SCREEN}")
    model = model_of(diag, runs, config)
    if criterion == SCREEN:
        models, skipped = screening_models(diag, model, dim, seed, config=config)
    else:
        models, skipped = leading_models(diag, leaders, dim)
        models = [(name, [eff]) for name, eff in models]
    for name, why in skipped:
        log.info(f"suggest: {name} left out ({why})")
    if len(models) < 2:
        raise TacestError("--suggest: no candidate besides the plain model can be predicted; nothing to tell apart")
    last = runs[-1]
    noise = _noise(diag, last)
    space = action_space_for(model, poke_style)
    target = model.centroid__world
    names = [m for m, _ in models]
    pairs = [("none", b) for b in names[1:]] if criterion == SCREEN else \
        [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]

    def pairwise(action) -> dict:
        """{"A vs B": [nats per draw of B]} (an empty dict if a prediction failed)."""
        preds = {}
        for name, sets in models:
            try:
                preds[name] = [predicted_measurements(model, action, eff, last.has_pose_obs) for eff in sets]
            except TacestError:
                return {}
        return {f"{a} vs {b}": [discrimination(preds[a][0], pb, noise) for pb in preds[b]] for a, b in pairs}

    def score(action) -> float:
        d = pairwise(action)
        if not d:
            return -math.inf
        if criterion == SCREEN:
            every = [v for ds in d.values() for v in ds]
            # ties (every drawn effect shown) broken by the weakest effect's showing
            return float(np.mean([math.log1p(min(v, SCREEN_DETECT)) for v in every])
                         + SCREEN_TIE_WEIGHT * math.log1p(min(every)))
        return math.log1p(min(ds[0] for ds in d.values()))

    lo, hi = space.bounds()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 31]))
    if dim == 3:  # every model's settled world once, inherited by the workers
        from tacest.information.expected import PREDICT_SUBSTEPS
        from tacest.information.expected3d import SETTLE_TIME, settled_world

        for _, sets in models:
            for eff in sets:
                settled_world(model, model.dt / PREDICT_SUBSTEPS, SETTLE_TIME, eff)
    cands, scores = [], []
    for f in space.searched_fingers():
        # each candidate's score is deterministic: forked copies of this process score
        # an iteration's candidates (tacest.parallel.forked_map), with the same result
        res = cem_maximize(lambda u: score(space.action(f, u, target)), lo, hi, rng, iterations=iterations,
                           population=population, elite=max(1, population // 3),
                           many=lambda U: forked_map(lambda u: score(space.action(f, u, target)), U))
        cands += [space.action(f, u, target) for u in res.samples]
        scores += list(res.scores)
    cands = np.asarray(cands, float)
    scores = np.where(np.isfinite(scores), np.asarray(scores, float), -1e300)
    order = np.argsort(-scores)
    chosen = []
    for i in order:
        if len(chosen) == n or scores[i] <= -1e300:
            break
        if all(np.linalg.norm(cands[i] - cands[j]) > 1e-6 for j in chosen):
            chosen.append(int(i))
    if not chosen:
        raise TacestError("--suggest: no candidate poke could be predicted under every model")
    out = []
    for i in chosen:
        plan = Plan(chosen=cands[i].copy(), candidates=cands, scores=scores, method="discriminate",
                    score="expected_llr", names=list(space.poke_names), kind="poke",
                    extra_attrs={"models": ",".join(names), "poke_style": poke_style, "criterion": criterion,
                                 "target": np.asarray(target, float)})
        pw = {p: float(np.mean(v)) for p, v in pairwise(cands[i]).items()}
        out.append(Suggestion(plan=plan, models=names, pairwise=pw, criterion=criterion))
    return out


def suggestion_writer(suggestions: list, json_obj: dict):
    """``extra(tmp)`` for tacest.diagnosis.report.write_report: the plan files
    ``suggest_<k>.h5`` (best first) and a section of report.md; adds ``suggestions`` to
    ``json_obj`` (file, models, chosen action, pairwise discrimination in nats) now, before
    the report writes it."""
    from tacest.io.plan import write_plan

    json_obj["suggestions"] = [
        {"file": f"suggest_{k}.h5", "models": s.models, "criterion": s.criterion, "chosen": s.plan.chosen_dict(),
         "pairwise_expected_llr": {p: float(v) for p, v in s.pairwise.items()}}
        for k, s in enumerate(suggestions, 1)]

    def write(tmp) -> list:
        names = []
        models = ", ".join(suggestions[0].models)
        why = (f"Pokes that would best show an effect of typical size (no effect shows yet): each of "
               f"{', '.join(suggestions[0].models[1:])} "
               "drawn from its typical range against the plain model" if suggestions[0].criterion == SCREEN
               else f"Pokes whose predicted measurements differ most between {models}")
        lines = ["", "## Suggested next experiments", "",
                 f"{why} (expected log-likelihood ratio, nats; `tacest record --plan suggest_<k>.h5` records one):",
                 "", "| file | approach (deg) | depth (m) | speed (m/s) | smallest pairwise |", "|---|---|---|---|---|"]

        def approach(c):
            if "approach_angle" in c:
                return f"{math.degrees(c['approach_angle']):.0f}"
            return f"azimuth {math.degrees(c['approach_azimuth']):.0f}, elevation {math.degrees(c['approach_elevation']):.0f}"

        for k, s in enumerate(suggestions, 1):
            name = f"suggest_{k}.h5"
            write_plan(s.plan, tmp / name)
            names.append(name)
            c = s.plan.chosen_dict()
            lines.append(f"| {name} | {approach(c)} | {c.get('depth', float('nan')):.3f} | "
                         f"{c.get('speed', float('nan')):.3f} | {min(s.pairwise.values()):.3g} |")
        with open(tmp / "report.md", "a") as fh:
            fh.write("\n".join(lines) + "\n")
        return names

    return write

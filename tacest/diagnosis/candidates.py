"""Candidate effects: one per SPEC effect name (``tacest.sim.effects.EFFECTS``).

Each candidate is a model augmentation with a few parameters:

- ``transform`` candidates (``latency``, ``time_scale``) change the data, not the NLP
  (tacest.diagnosis.transforms); their parameter is chosen by a line search on a grid of
  values, one fit to all data per value tried, and counts as one parameter;
- ``nlp`` candidates (every other effect) are extra parameters inside the estimator's
  NLP (``estimate_runs(..., effects=(name,))``); they need an estimator that offers them.

Screening signatures.  Each effect leaves its mark on some loss terms first (e.g. a
force bias on the force residual where the finger does not touch); :func:`signature_scores`
ranks candidates by the share of the flagged excess on their terms.  This ranking is
only used to choose which candidates to refit when their number is limited
(``max_candidates``) and to choose the first latency value to fit; it never decides the
verdict.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tacest.errors import TacestError
from tacest.model.effects_contact import RESTITUTION_START

#: data-transform candidates: the values their parameter may take (sorted), and the
#: value that means "no effect".  Latency: whole samples, SPEC draws 1-4, one more for
#: margin.  Time scale: SPEC draws 1 ± U(0.02, 0.05); steps of about 1.5 %.
TRANSFORM_GRIDS = {
    "latency": (1, 2, 3, 4, 5),
    "time_scale": (0.95, 0.965, 0.98, 1.02, 1.035, 1.05),
}
TRANSFORM_IDENTITY = {"latency": 0, "time_scale": 1.0}
#: the first values fitted when no screening orders them (time scale: both sides of 1)
TRANSFORM_START = {"latency": (1,), "time_scale": (0.965, 1.035)}

#: effects whose fit started at "no effect" stays in the plain model's basin, with the
#: strength their extra start is made at (physical units, estimate /params names).  A
#: bounce is a change of contact mode, not a continuous deformation of the trajectory:
#: from the plain fit's trajectory (which lands and stays) a small restitution only adds
#: cost, so e runs back to 0.  On the benchmark's restitution recording (truth e 0.42)
#: the fits started at e = 0 ended at objective 2329 with e = 0, the plain fit at 2245;
#: trajectories from the pose observations with every parameter held and e = 0.5, then
#: everything freed, reach the basin of the truth (1025-1125).  See typical_start_fit.
TYPICAL_STARTS = {"restitution": {"restitution.e": RESTITUTION_START}}

#: loss terms where each effect shows first (screening, report)
SIGNATURE_TERMS = {
    "restitution": ("dynamics", "complementarity", "penetration"),
    "angular_damping": ("dynamics",),
    "linear_drag": ("dynamics", "dissipation"),
    "soft_contact": ("penetration", "complementarity"),
    "force_bias": ("force",),
    "force_scale": ("force", "dynamics"),
    "latency": ("contact", "normal", "cone"),
    "face_friction": ("dynamics", "dissipation"),
    "com_offset": ("dynamics", "contact"),
    "time_scale": ("dynamics",),
}


@dataclass(frozen=True)
class Candidate:
    """A candidate effect: ``name`` (SPEC), ``kind`` (``transform`` | ``nlp``),
    ``param_names`` and their number ``n_params`` (the penalty counts them)."""

    name: str
    kind: str
    param_names: tuple
    n_params: int


def candidate(name: str, n_vertices: int = 4, dim: int = 2) -> Candidate:
    """The candidate for SPEC effect ``name`` (TacestError for an unknown or ``none``).

    n_vertices: of the fitted shape (face_friction has one coefficient per face)."""
    from tacest.sim.effects import EFFECTS, NONE, valid_names_text

    if name not in EFFECTS:
        raise TacestError(f"unknown effect {name!r}; valid effects: {valid_names_text()}")
    if name == NONE:
        raise TacestError("'none' is not a candidate effect (it is the model as it is)")
    spec = EFFECTS[name]
    names = tuple(spec.param_names)
    if name == "face_friction":
        n = int(n_vertices)
    elif name in ("force_bias", "com_offset"):
        n = dim  # one offset per axis (2-D: x, y)
        names = names[:dim]
    else:
        n = len(names)
    kind = "transform" if name in TRANSFORM_GRIDS else "nlp"
    return Candidate(name=name, kind=kind, param_names=names, n_params=n)


def parse_effect_list(text) -> tuple:
    """``a,b,c`` (or a list) -> tuple of candidate names, checked; None or empty -> every
    SPEC effect but ``none``."""
    from tacest.sim.effects import EFFECT_NAMES, NONE

    if text is None or (isinstance(text, str) and not text.strip()):
        return tuple(n for n in EFFECT_NAMES if n != NONE)
    items = text.split(",") if isinstance(text, str) else list(text)
    names = []
    for item in items:
        n = str(item).strip()
        if not n:
            continue
        candidate(n)  # validates
        if n not in names:
            names.append(n)
    if not names:
        raise TacestError("--effects: no effect named")
    return tuple(names)


def signature_scores(stats: list, names) -> dict:
    """{effect: share of the flagged excess on its signature terms} from window tests
    (tacest.estimation.floor.window_tests)."""
    flagged = [s for s in stats if s.flagged]
    total = sum(max(s.excess, 0.0) for s in flagged)
    out = {}
    for n in names:
        terms = SIGNATURE_TERMS.get(n, ())
        mine = sum(max(s.excess, 0.0) for s in flagged if s.term in terms)
        out[n] = float(mine / total) if total > 0 else 0.0
    return out


# ------------------------------------------------------------------------------------
# latency screening: how well the fitted geometry agrees with shifted contact flags


def latency_mismatch(runs: list, estimate, sigma_gap: float, max_shift: int = None) -> dict:
    """{k: mismatch} for tactile shifts k = 0..max_shift (samples), from a fit of the
    unshifted runs: Σ over fingers and samples of (gap / sigma_gap)² where the shifted
    flag says contact and the fitted gap is open at both ends of the sample's interval
    (the smaller of the two counts), and (overlap / sigma_gap)² where it says no
    contact and the fitted finger is inside the object.

    runs : the runs of ``estimate`` (same order and lengths); estimate : Estimate with
    vertices and per-run poses; sigma_gap : m.  Cheap (no solve); it ranks latency grid
    values only.
    """
    from tacest.estimation.initial import finger_gaps

    kmax = max(TRANSFORM_GRIDS["latency"]) if max_shift is None else int(max_shift)
    V = np.asarray(estimate.vertices, float)
    out = {k: 0.0 for k in range(kmax + 1)}
    for run, rest in zip(runs, estimate.runs):
        if run.contact is None:
            continue
        pose = np.asarray(rest.pose, float)[:, :3]
        gaps = finger_gaps(run, V, pose) / sigma_gap  # (T, F)
        valid = ~run.finger_missing_mask
        c = run.contact.astype(bool)
        T = run.n_samples
        # a flag covers the interval (t-1, t]: touching at either end counts (SPEC)
        g_int = np.minimum(gaps, np.vstack([gaps[:1], gaps[:-1]]))
        for k in range(kmax + 1):
            if k >= T:
                continue
            ck = c[k:]
            ok = valid[k:] & valid[: T - k]
            on = np.where(ck & ok, np.maximum(g_int[: T - k], 0.0), 0.0)
            off = np.where(~ck & ok, np.minimum(gaps[: T - k], 0.0), 0.0)
            # per sample, so that shifts (which drop k samples) compare fairly
            out[k] += float(np.sum(on ** 2 + off ** 2)) / max(T - k, 1) * T
    return out


#: objective units (a negative log-likelihood): latency values whose fits to all data are
#: within this of the best are indistinguishable (likelihood ratio e^-1), and the smallest
#: of them is chosen.  A flag covers the interval (t-1, t], so a shift one sample too far
#: costs almost nothing (the shape absorbs it) and the plain minimum is biased late.
LATENCY_TIE = 1.0


def choose_transform_value(name: str, objectives: dict):
    """The grid value to keep among {value: objective of the fit to all data}: the
    minimum, except for latency the smallest delay within LATENCY_TIE of it."""
    ok = {v: o for v, o in objectives.items() if o is not None and np.isfinite(o)}
    if not ok:
        raise TacestError(f"{name}: no fit to choose from")
    best = min(ok, key=ok.get)
    if name == "latency":
        return min(v for v, o in ok.items() if o <= ok[best] + LATENCY_TIE)
    return best


def first_transform_values(name: str, screening: dict = None) -> list:
    """The values to fit first: latency, the delay the screening signature ranks best
    (k >= 1); time scale, both sides of 1."""
    if name == "latency" and screening:
        ranked = sorted((k for k in TRANSFORM_GRIDS["latency"] if k in screening), key=lambda k: screening[k])
        if ranked:
            return [ranked[0]]
    return list(TRANSFORM_START[name])


def next_transform_value(name: str, objectives: dict):
    """The next value to fit (a line search on the grid), or None when the best value
    so far has both grid neighbours fitted (a bracketed minimum) or has none left.

    objectives : {value: objective of the fit to all data}, the identity value (no
    effect: the plain model) included.  From the best value, fit its unfitted neighbour;
    when both are unfitted, the one farther from the identity (a fit of the plain model
    pulls the screening toward small effects)."""
    grid = sorted(set(TRANSFORM_GRIDS[name]) | {TRANSFORM_IDENTITY[name]})
    ok = {v: o for v, o in objectives.items() if o is not None and np.isfinite(o)}
    tried = set(objectives)
    if not ok:
        return None
    best = min(ok, key=ok.get)
    i = grid.index(best) if best in grid else int(np.argmin([abs(g - best) for g in grid]))
    nbrs = [grid[j] for j in (i - 1, i + 1) if 0 <= j < len(grid) and grid[j] not in tried]
    if not nbrs:
        return None
    ident = TRANSFORM_IDENTITY[name]
    return max(nbrs, key=lambda v: abs(v - ident))

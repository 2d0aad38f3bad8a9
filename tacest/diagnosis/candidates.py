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
(``max_candidates``); the first latency value to fit comes from a profile of quick fits
over the delays (LATENCY_SCREEN).  Neither decides the verdict.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tacest.errors import TacestError
from tacest.model.effects_contact import RESTITUTION_START

#: data-transform candidates: the values their parameter may take (sorted), and the
#: value that means "no effect".  The ranges are set by the sensors and clocks such a
#: rig has, not by the simulator's draws (which are wider than both, docs/effects.md):
#:
#: - latency, whole samples 1..LATENCY_MAX_SAMPLES: a tactile stream reaches the
#:   recorder through a serial or USB link that buffers a frame or two, and a camera-
#:   based tactile sensor (a gel imaged at 30-60 frames/s, its flow computed before the
#:   contact is reported) lags by 2-6 frames, i.e. 50-200 ms; at the rig's and the
#:   simulator's 100 Hz that is up to 20 samples;
#: - time scale s (a clock running at s times the true rate) on a grid of 1.5 % steps to
#:   ±TIME_SCALE_SPAN: an uncalibrated microcontroller RC oscillator is specified to
#:   ±10 %, and a camera whose frames are stamped at their nominal rate while it drops
#:   frames in poor light is off by more.  A length scale error L (positions L times
#:   the true ones: a camera calibrated with the wrong target size) is the same data to
#:   the model as a clock error s = 1/sqrt(L): both make every acceleration L (= 1/s^2)
#:   times the true one (gravity, the contacts', the finger's forces over the mass),
#:   and velocities, sizes and paths are free in the fit; so ±18 % of clock covers
#:   -28 % .. +49 % of length (tested on synthetic free falls of both kinds).  The
#:   grid's resolution, 1.5 %, is what the objective resolves on a free fall (one
#:   step; tests/test_diagnose.py).  The span was ±12 % until 2026-11-27: a 3-D toss
#:   recording's clock at 1.12 sat on its edge, and other simulators draw up to 15 %.
LATENCY_MAX_SAMPLES = 20
TIME_SCALE_STEP = 0.015
TIME_SCALE_SPAN = 0.18
TRANSFORM_GRIDS = {
    "latency": tuple(range(1, LATENCY_MAX_SAMPLES + 1)),
    "time_scale": tuple(sorted({round(1.0 + sign * TIME_SCALE_STEP * j, 6)
                                for j in range(1, int(round(TIME_SCALE_SPAN / TIME_SCALE_STEP)) + 1)
                                for sign in (-1.0, 1.0)})),
}
TRANSFORM_IDENTITY = {"latency": 0, "time_scale": 1.0}
#: the first values fitted when no screening orders them (time scale: both sides of 1,
#: three steps out, so that a parabola through them and the plain fit (s = 1) resolves a
#: minimum inside and extrapolates to one outside: next_transform_value)
TRANSFORM_START = {"latency": (1,), "time_scale": (round(1.0 - 3 * TIME_SCALE_STEP, 6),
                                                    round(1.0 + 3 * TIME_SCALE_STEP, 6))}

#: effects whose fit started at "no effect" stays in the plain model's basin, with the
#: strength their extra start is made at (physical units, estimate /params names, from
#: the plain fit).  A
#: bounce is a change of contact mode, not a continuous deformation of the trajectory:
#: from the plain fit's trajectory (which lands and stays) a small restitution only adds
#: cost, so e runs back to 0.  On the benchmark's restitution recording (truth e 0.42)
#: the fits started at e = 0 ended at objective 2329 with e = 0, the plain fit at 2245;
#: trajectories from the pose observations with every parameter held and e = 0.5, then
#: everything freed, reach the basin of the truth (1025-1125).  See typical_start_fit.
#: The typical strength, 0.5 (model.effects_contact.RESTITUTION_START), is the middle of
#: the coefficient's physical range [0, 0.95], not a value of the simulator's draws (which
#: run from 0.05 to 0.9).
#: A soft ground is the same kind of change (the object rests in the ground, an impact
#: sinks it): on toss-design seed 3 (truth 4570 N/m, the object's weight sinks it 0.87 mm)
#: the warm start stayed at compliance 1.8e-10 m/N (objective 1852, the plain fit 1902)
#: and gained on held-out data through the plate's slack alone; started at a sink of 1 %
#: of the object's size under its weight (and at 1/3000 or 1/1000 m/N alike) it reached
#: 5590 N/m at objective 1460.  On clean recordings that start ends worse than the warm
#: one (seeds 0, 3, 5, 20, 21; and force_scale seed 3), so the best of the starts stays
#: the warm fit there.
SOFT_START_SINK_FRACTION = 0.01


def _soft_contact_start(plain) -> dict:
    """soft_contact's typical start for a plain estimate (mass kg, vertices m): the ground
    sinks by SOFT_START_SINK_FRACTION of the object's largest extent under its weight,
    its plate's time constant one tau unit (10 ms)."""
    from tacest.model.effects_contact import TAU_UNIT, compliance_for_sink

    size = float(np.max(np.ptp(np.asarray(plain.vertices, float), axis=0)))
    return {"soft_contact.compliance": compliance_for_sink(SOFT_START_SINK_FRACTION * size, plain.params["mass"]),
            "soft_contact.tau": TAU_UNIT}


#: effect -> its typical start for a plain estimate: {estimate /params name: value}
TYPICAL_STARTS = {"restitution": lambda plain: {"restitution.e": RESTITUTION_START},
                  "soft_contact": _soft_contact_start}

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
# latency screening: a profile of quick fits over the delays

#: delays (samples) of the screening profile: quick fits of the plain model to the data
#: with the tactile streams advanced by k (warm-started from the plain fit, the
#: diagnosis' fit budget, no restarts; diagnose._latency_profile), every delay up to 4
#: (a small delay's knee must be found to one sample), then about 30 % apart up to the
#: grid's end.  Why fits: the objective against k falls steeply up to the true delay and
#: stays on a shelf beyond it (a flag covers the interval (t-1, t], and the shape absorbs
#: a little of a longer shift): on a 2-poke recording 275, 230, 180, 86, 38.5 at k = 0,
#: 3, 6, 10, 14 and 34.5-34.7 from k = 15 to 20 for a true 15.  A geometric signature
#: from the plain fit (no solve; the screening until the grid went past 5 samples)
#: ranked k = 0 first for true delays of 8 and 15 samples: the plain fit had moved the
#: object to meet the unshifted flags.
LATENCY_SCREEN = (1, 2, 3, 4, 6, 8, 11, 14, 17, 20)


def latency_screen_values(shortest_run: int) -> tuple:
    """The screening delays a recording whose shortest run has ``shortest_run`` samples
    can take (undo_latency needs k < its length)."""
    return tuple(k for k in LATENCY_SCREEN if k < int(shortest_run))


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
    """The values to fit first: latency, the delay the screening profile ({k: objective
    of a quick fit}) puts at the knee (the smallest k within LATENCY_TIE of its lowest,
    as choose_transform_value keeps); time scale, both sides of 1."""
    if name == "latency" and screening:
        prof = {k: o for k, o in screening.items() if k in TRANSFORM_GRIDS["latency"]}
        if any(o is not None and np.isfinite(o) for o in prof.values()):
            return [choose_transform_value("latency", prof)]
    return list(TRANSFORM_START[name])


def next_transform_value(name: str, objectives: dict):
    """The next value to fit (a line search on the grid), or None when it has nothing
    left to bracket.

    objectives : {value: objective of the fit to all data}, the identity value (no
    effect: the plain model) included.

    Latency: the objective falls up to the true delay and stays on a shelf beyond it
    (LATENCY_SCREEN), and the delay kept is the smallest within LATENCY_TIE of the
    lowest (choose_transform_value): from that value, fit the delay one sample shorter
    (is the knee lower?), else one sample longer (is the shelf reached?), else stop.

    Time scale (a smooth minimum): from the best value, on the side of an unfitted grid
    neighbour, the grid value nearest the vertex of the parabola through the three
    lowest values fitted (in value², parabola_vertex), where that parabola is convex and its vertex lies beyond the
    best value on that side (a minimum not yet bracketed: with a budget of three fits a
    walk of one grid step at a time reached at most two steps past the starts, so a 7 %
    clock error was out of reach); otherwise the unfitted neighbour, the one farther
    from the identity when both are."""
    grid = sorted(set(TRANSFORM_GRIDS[name]) | {TRANSFORM_IDENTITY[name]})
    ok = {v: o for v, o in objectives.items() if o is not None and np.isfinite(o)}
    tried = set(objectives)
    ident = TRANSFORM_IDENTITY[name]
    if name == "latency":
        effect = {v: o for v, o in ok.items() if v != ident}
        if not effect:  # no delay fitted yet (or every fit failed): the shortest untried
            left = [v for v in grid if v != ident and v not in tried]
            return min(left) if left else None
        anchor = choose_transform_value(name, effect)
        for v in (anchor - 1, anchor + 1):
            if v in grid and v not in tried:
                return v
        return None
    if not ok:
        return None
    best = min(ok, key=ok.get)
    i = grid.index(best) if best in grid else int(np.argmin([abs(g - best) for g in grid]))
    nbrs = [grid[j] for j in (i - 1, i + 1) if 0 <= j < len(grid) and grid[j] not in tried]
    if not nbrs:
        return None
    vertex = parabola_vertex(ok, squared=name == "time_scale")
    if vertex is not None:
        for side in (-1, 1):
            n = grid[i + side] if 0 <= i + side < len(grid) else None
            if n is None or n in tried or (vertex - best) * side <= 0:
                continue
            beyond = [g for g in grid if (g - best) * side > 0 and g not in tried]
            return min(beyond, key=lambda g: (abs(g - vertex), abs(g - best)))
    return max(nbrs, key=lambda v: abs(v - ident))


def parabola_vertex(objectives: dict, squared: bool = False):
    """Vertex (the minimizing value) of the parabola through the three lowest of
    {value: objective}, or None with fewer than three values or a parabola that is not
    convex (a maximum, a line).  ``squared``: the parabola in value² (values > 0), the
    coordinate a clock error's misfit is quadratic in: a clock at s times the true rate
    and a correction v leave accelerations v²/s² times the true ones, residuals linear
    in v² (a parabola in v itself overshoots a 12 % error by two grid steps)."""
    pts = sorted(objectives.items(), key=lambda t: t[1])[:3]
    if len(pts) < 3:
        return None
    x = np.array([p[0] for p in pts], float)
    y = np.array([p[1] for p in pts], float)
    if len(set(x)) < 3:
        return None
    if squared:
        x = x * x
    a, b, _ = np.polyfit(x - x.mean(), y, 2)
    if not a > 0:
        return None
    vertex = float(x.mean() - b / (2 * a))
    if squared:
        return float(np.sqrt(vertex)) if vertex > 0 else None
    return vertex

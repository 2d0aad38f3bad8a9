"""The registry of unmodelled effects (SPEC "Effect names") and their parsing.

This module is the one place that says which effects exist, what parameters each
has (names, units, hard bounds, typical random draws) and where it acts.  The
simulator injects them (``tacest.sim.world`` for physics, ``tacest.sim.record`` for
the sensor and the clock, ``tacest.sim.objects`` for the mass distribution); the
estimator's diagnosis can import the same registry (it needs no pymunk) to build
its candidate models and parameter bounds.  docs/effects.md describes each effect.

An effect is written ``NAME[:key=value,...]`` on the command line (e.g.
``latency:samples=2`` or ``force_bias:fx=0.2,fy=-0.1``); parameters that are not
given are drawn at random, seeded, from the effect's typical range.  In a run file's
``/truth`` attrs ``effects`` the resolved effects are stored as JSON: ``{"name":
"none"}`` when clean, one object ``{"name": ..., param: value, ...}`` for one effect,
a list of such objects for several.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from tacest.errors import TacestError

#: The name of "no unmodelled effect" (SPEC).
NONE = "none"


@dataclass(frozen=True)
class EffectContext:
    """What a random parameter draw may depend on: the object it acts on.

    mass : kg; inertia : kg·m² about the COM (3-D: the mean principal moment); inradius :
    m, radius of the largest circle (sphere) about the centroid inside the shape;
    n_faces : number of polygon (polytope) faces; friction_ground : nominal ground
    friction coefficient; dim : 2 or 3, the world the effect acts in (parameters of
    the other dimension are not drawn, see EffectParam.dims).
    """

    mass: float = 0.5
    inertia: float = 1e-3
    inradius: float = 0.03
    n_faces: int = 4
    friction_ground: float = 0.5
    dim: int = 2


@dataclass(frozen=True)
class EffectParam:
    """One parameter of an effect.

    bounds : (low, high) hard limits, inclusive; explicit values outside are an error
        (an estimator may use them as optimisation bounds).
    typical : text describing the random draw (docs and ``--help``).
    draw : ``draw(rng, ctx, params) -> value`` for a random, plausible value; ``params``
        holds the effect's parameters resolved so far (in declaration order).
    kind : ``"float"``, ``"int"`` or ``"list"`` (a list of floats, one per face,
        written ``a;b;c`` on the command line).
    dims : the world dimensions the parameter exists in (``(3,)``: 3-D only, e.g. a
        z component); declared after the parameters of both, so adding one never
        changes the draws of a 2-D effect.
    """

    name: str
    unit: str
    bounds: tuple
    typical: str
    doc: str
    draw: Callable[[np.random.Generator, EffectContext, dict], object]
    kind: str = "float"
    dims: tuple = (2, 3)


@dataclass(frozen=True)
class EffectSpec:
    """An effect: where it acts (``contact``, ``body``, ``ground``, ``sensor``,
    ``clock``, ``object``), what it does, and its parameters."""

    name: str
    where: str
    doc: str
    params: tuple = ()

    @property
    def param_names(self) -> tuple:
        return tuple(p.name for p in self.params)

    def param(self, name) -> EffectParam:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)


def _signed(lo, hi):
    """Draw s·U(lo, hi) with a random sign s: clearly away from zero."""
    return lambda rng, ctx, params: float(rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi))


def _around_one(lo, hi):
    """Draw 1 ± U(lo, hi): a gain clearly different from one."""
    return lambda rng, ctx, params: float(1.0 + rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi))


def _draw_face_values(rng, ctx: EffectContext, params):
    # per-face coefficients spread around the nominal ground friction; alternate the
    # sign of the deviation so that neighbouring faces always differ clearly
    mu = ctx.friction_ground
    dev = rng.uniform(0.3, 0.6, size=ctx.n_faces)
    sign = np.where(np.arange(ctx.n_faces) % 2 == 0, 1.0, -1.0) * rng.choice([-1.0, 1.0])
    return [float(v) for v in np.clip(mu * (1.0 + sign * dev), 0.05, 1.5)]


def _draw_soft_damping(rng, ctx: EffectContext, params):
    # 0.5-1 times the critical damping 2·sqrt(k·m) of the object on the drawn spring
    return float(2.0 * math.sqrt(params["stiffness"] * ctx.mass) * rng.uniform(0.5, 1.0))


def _uniform(lo, hi):
    return lambda rng, ctx, params: float(rng.uniform(lo, hi))


#: random draws of the effects whose diagnosis searches a range (docs/effects.md): the
#: latency wider than that search on purpose (tacest.diagnosis.candidates.TRANSFORM_GRIDS:
#: latency 1-20 samples, clock ±18 %; restitution is searched from 0), so that a benchmark
#: drawing from them measures what the diagnosis does at and beyond the edges of its
#: ranges, not only inside them; the clock draws reach 15 %, near the search's edge.  Restitution: from nearly plastic (0.05) to a rubber ball (0.9).
RESTITUTION_DRAW = (0.05, 0.9)
#: samples, inclusive (at 100 Hz: 10-250 ms)
LATENCY_DRAW = (1, 25)
#: |scale - 1|
TIME_SCALE_DRAW = (0.02, 0.15)


_REGISTRY = [
    EffectSpec(NONE, "nowhere", "The recording follows the estimator's model: no unmodelled effect."),
    EffectSpec(
        "restitution", "contact",
        "Bouncy impacts: the object's contacts (ground and finger) have a coefficient of "
        "restitution e > 0, so the object bounces instead of landing plastically.",
        (EffectParam("e", "1", (0.0, 0.95), "U(0.05, 0.9)", "coefficient of restitution",
                     _uniform(*RESTITUTION_DRAW)),),
    ),
    EffectSpec(
        "angular_damping", "body",
        "A torque -c·ω on the object (air, a rolling bearing under it): spin dies out.",
        (EffectParam("c", "N·m·s", (0.0, 1.0), "I/τ with τ ~ U(0.1, 0.5) s",
                     "damping coefficient", lambda rng, ctx, params: float(ctx.inertia / rng.uniform(0.1, 0.5))),),
    ),
    EffectSpec(
        "linear_drag", "body",
        "A force -b·v on the object's centre of mass: sliding slows more than friction says.",
        (EffectParam("b", "N·s/m", (0.0, 100.0), "m/τ with τ ~ U(0.2, 1) s",
                     "drag coefficient", lambda rng, ctx, params: float(ctx.mass / rng.uniform(0.2, 1.0))),),
    ),
    EffectSpec(
        "soft_contact", "ground",
        "A compliant ground: the table top is a plate on a damped spring, so the object "
        "sinks below y = 0 by load/stiffness (more when the finger pushes down).",
        (EffectParam("stiffness", "N/m", (100.0, 1e6), "U(1500, 6000)", "spring stiffness of the ground",
                     _uniform(1500.0, 6000.0)),
         EffectParam("damping", "N·s/m", (0.0, 1e4), "0.5-1 × critical for the object's mass",
                     "damper of the ground", _draw_soft_damping)),
    ),
    EffectSpec(
        "force_bias", "sensor",
        "A constant offset (fx, fy) added to every sample of the measured force stream, "
        "with or without contact (an uncalibrated sensor zero).",
        (EffectParam("fx", "N", (-100.0, 100.0), "±U(0.1, 0.4)", "x offset, world frame", _signed(0.1, 0.4)),
         EffectParam("fy", "N", (-100.0, 100.0), "±U(0.1, 0.4)", "y offset, world frame", _signed(0.1, 0.4)),
         EffectParam("fz", "N", (-100.0, 100.0), "±U(0.1, 0.4)", "z offset, world frame (3-D only)",
                     _signed(0.1, 0.4), dims=(3,))),
    ),
    EffectSpec(
        "force_scale", "sensor",
        "A wrong gain on the measured force: the stream is gain × the true force.",
        (EffectParam("gain", "1", (0.1, 10.0), "1 ± U(0.15, 0.35)", "force sensor gain", _around_one(0.15, 0.35)),),
    ),
    EffectSpec(
        "latency", "sensor",
        "The tactile streams (contact, force, normal) arrive a whole number of samples late "
        "relative to the fingertip positions; the first samples read 'no contact'.",
        (EffectParam("samples", "samples", (1, 1000), "integer U{1, 25}", "delay in samples",
                     lambda rng, ctx, params: int(rng.integers(LATENCY_DRAW[0], LATENCY_DRAW[1] + 1)),
                     kind="int"),),
    ),
    EffectSpec(
        "face_friction", "contact",
        "The ground friction differs from face to face of the object: the coefficient of "
        "the object-ground contact is that of the face that faces the ground most.",
        (EffectParam("values", "1", (0.01, 3.0), "μ_ground·(1 ± U(0.3, 0.6)), alternating sign",
                     "one coefficient per face; face i runs from body-frame vertex i to i+1",
                     _draw_face_values, kind="list"),),
    ),
    EffectSpec(
        "com_offset", "object",
        "The centre of mass is away from the shape's centroid (non-uniform density). "
        "The truth vertices are in the COM frame, so they are shifted by -(dx, dy); "
        "the inertia about the COM stays that of the uniform shape about its centroid.",
        (EffectParam("dx", "m", (-0.5, 0.5), "±U(0.25, 0.45)·inradius",
                     "x of the COM in the centroid frame (object axes)",
                     lambda rng, ctx, params: float(rng.choice([-1.0, 1.0]) * rng.uniform(0.25, 0.45) * ctx.inradius)),
         EffectParam("dy", "m", (-0.5, 0.5), "±U(0, 0.3)·inradius",
                     "y of the COM in the centroid frame (object axes)",
                     lambda rng, ctx, params: float(rng.choice([-1.0, 1.0]) * rng.uniform(0.0, 0.3) * ctx.inradius)),
         EffectParam("dz", "m", (-0.5, 0.5), "±U(0, 0.3)·inradius",
                     "z of the COM in the centroid frame (object axes; 3-D only)",
                     lambda rng, ctx, params: float(rng.choice([-1.0, 1.0]) * rng.uniform(0.0, 0.3) * ctx.inradius),
                     dims=(3,))),
    ),
    EffectSpec(
        "time_scale", "clock",
        "The recorder's clock runs fast or slow: the written /time and dt are scale × the "
        "true ones (positions, forces and sample counts are unchanged).",
        (EffectParam("scale", "1", (0.5, 2.0), "1 ± U(0.02, 0.15)", "clock rate error",
                     _around_one(*TIME_SCALE_DRAW)),),
    ),
]

#: name -> EffectSpec, in SPEC order
EFFECTS: dict = {spec.name: spec for spec in _REGISTRY}

#: every valid effect name, SPEC order ("none" first)
EFFECT_NAMES: tuple = tuple(EFFECTS)


@dataclass
class Effect:
    """One resolved effect: its ``name`` and a value for every parameter."""

    name: str
    params: dict = field(default_factory=dict)

    @property
    def spec(self) -> EffectSpec:
        """Its registry entry, restricted to the parameters it has (those of its
        world's dimension: a 2-D force_bias has no fz)."""
        spec = EFFECTS[self.name]
        if all(p.name in self.params for p in spec.params):
            return spec
        return EffectSpec(spec.name, spec.where, spec.doc, tuple(p for p in spec.params if p.name in self.params))

    def to_json_obj(self) -> dict:
        """``{"name": ..., param: value, ...}`` (the SPEC /truth form of one effect)."""
        return {"name": self.name, **self.params}

    def __getitem__(self, key):
        return self.params[key]


def valid_names_text() -> str:
    return ", ".join(EFFECT_NAMES)


def _parse_value(effect: str, p: EffectParam, text: str):
    where = f"effect {effect}: {p.name}={text}"
    try:
        if p.kind == "int":
            val = float(text)
            if val != round(val):
                raise ValueError
            return int(round(val))
        if p.kind == "list":
            parts = [s for s in text.replace("|", ";").split(";") if s.strip()]
            if not parts:
                raise ValueError
            return [float(s) for s in parts]
        return float(text)
    except ValueError:
        kind = {"int": "an integer", "list": "a list of numbers separated by ';'"}.get(p.kind, "a number")
        raise TacestError(f"{where} is not {kind}") from None


def _check_bounds(effect: str, p: EffectParam, value):
    values = value if isinstance(value, list) else [value]
    lo, hi = p.bounds
    for v in values:
        if not (math.isfinite(v) and lo <= v <= hi):
            raise TacestError(f"effect {effect}: {p.name}={v} is outside [{lo}, {hi}] ({p.unit})")


def parse_effect(text: str) -> tuple:
    """Parse ``NAME[:key=value,...]`` into ``(name, {key: value})`` (explicit values only).

    Raises TacestError naming the valid effects (unknown name) or the valid keys
    (unknown key), or saying which value is malformed or out of bounds.
    """
    text = text.strip()
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in EFFECTS:
        raise TacestError(f"unknown effect {name!r}; valid effects: {valid_names_text()}")
    spec = EFFECTS[name]
    given = {}
    if rest.strip():
        for item in rest.split(","):
            if not item.strip():
                continue
            key, eq, val = item.partition("=")
            key = key.strip()
            if not eq:
                raise TacestError(f"effect {name}: expected key=value, got {item.strip()!r}")
            if key not in spec.param_names:
                valid = ", ".join(spec.param_names) or "(none: it takes no parameters)"
                raise TacestError(f"effect {name} has no parameter {key!r}; valid: {valid}")
            if key in given:
                raise TacestError(f"effect {name}: parameter {key!r} given twice")
            p = spec.param(key)
            value = _parse_value(name, p, val.strip())
            _check_bounds(name, p, value)
            given[key] = value
    return name, given


def resolve_effect(name: str, given: dict, rng: np.random.Generator, ctx: EffectContext) -> Effect:
    """Fill the parameters of effect ``name`` that ``given`` lacks with seeded random draws.

    ``ctx`` describes the object (typical draws scale with its mass, inertia and size)
    and the world's dimension (parameters of the other dimension are an error when
    given and are not drawn).  Checks that face_friction has one value per face.
    """
    spec = EFFECTS[name]
    used = [p for p in spec.params if int(ctx.dim) in p.dims]
    for key in given:
        if key not in {p.name for p in used}:
            raise TacestError(f"effect {name}: parameter {key!r} is not used in {int(ctx.dim)}-D; "
                              f"valid: {', '.join(p.name for p in used)}")
    params = {p.name: given[p.name] for p in used if p.name in given}
    for p in used:  # declaration order: later draws may depend on earlier values
        if p.name not in params:
            params[p.name] = p.draw(rng, ctx, params)
    if name == "face_friction" and len(params["values"]) != ctx.n_faces:
        raise TacestError(f"effect face_friction: values has {len(params['values'])} entries, "
                          f"the object has {ctx.n_faces} faces")
    ordered = {p.name: params[p.name] for p in used}
    return Effect(name, ordered)


def resolve_effects(items, seed: int, ctx: EffectContext) -> list:
    """Turn command-line texts (or Effect objects, kept as they are) into resolved effects.

    items : list of ``str`` (``NAME[:key=value,...]``) or :class:`Effect`;
    seed : int >= 0; effect i draws from its own stream (seed, i), so adding an effect
        never changes the object, the pokes or the noise of a recording.
    Returns a list without ``none``; several effects of the same name are an error.
    """
    effects, seen = [], set()
    for i, item in enumerate(items):
        if isinstance(item, Effect):
            name, given = item.name, dict(item.params)
            if name not in EFFECTS:
                raise TacestError(f"unknown effect {name!r}; valid effects: {valid_names_text()}")
        else:
            name, given = parse_effect(str(item))
        if name == NONE:
            continue
        if name in seen:
            raise TacestError(f"effect {name} given more than once")
        seen.add(name)
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7, i]))
        effects.append(resolve_effect(name, given, rng, ctx))
    return effects


def find(effects, name) -> Optional[Effect]:
    """The effect called ``name`` in a list of effects, or None."""
    for e in effects:
        if e.name == name:
            return e
    return None


def effects_to_json(effects) -> str:
    """The SPEC /truth attrs ``effects`` string: ``{"name": "none"}``, one object, or a list."""
    objs = [e.to_json_obj() for e in effects]
    if not objs:
        return json.dumps({"name": NONE})
    return json.dumps(objs[0] if len(objs) == 1 else objs, sort_keys=True)


def effects_from_json(value) -> list:
    """Effects from the /truth form: a JSON string, a dict or a list of dicts.

    Every name and parameter is checked against the registry (missing parameters
    are an error here: stored effects are always fully resolved; only a parameter of
    one dimension, e.g. force_bias fz, may be absent).  ``none`` entries are dropped.
    """
    if isinstance(value, (str, bytes)):
        try:
            value = json.loads(value)
        except json.JSONDecodeError:
            raise TacestError("effects: not valid JSON") from None
    if isinstance(value, dict):
        value = [value]
    if not isinstance(value, list):
        raise TacestError("effects: expected a JSON object or a list of objects")
    out = []
    for obj in value:
        if not isinstance(obj, dict) or "name" not in obj:
            raise TacestError(f"effects: each entry needs a 'name', got {obj!r}")
        name = obj["name"]
        if name not in EFFECTS:
            raise TacestError(f"unknown effect {name!r}; valid effects: {valid_names_text()}")
        if name == NONE:
            continue
        spec = EFFECTS[name]
        params = {}
        for p in spec.params:
            if p.name not in obj:
                if tuple(p.dims) != (2, 3):  # a parameter of the other world's dimension
                    continue
                raise TacestError(f"effect {name}: parameter {p.name!r} is missing")
            v = obj[p.name]
            v = [float(x) for x in v] if p.kind == "list" else (int(v) if p.kind == "int" else float(v))
            _check_bounds(name, p, v)
            params[p.name] = v
        unknown = set(obj) - set(spec.param_names) - {"name"}
        if unknown:
            raise TacestError(f"effect {name} has no parameter {sorted(unknown)[0]!r}; "
                              f"valid: {', '.join(spec.param_names)}")
        out.append(Effect(name, params))
    return out


def describe() -> str:
    """A plain-text table of every effect and its parameters (for ``--help`` and docs)."""
    lines = []
    for spec in EFFECTS.values():
        lines.append(f"{spec.name} [{spec.where}]: {spec.doc}")
        for p in spec.params:
            only = "" if tuple(p.dims) == (2, 3) else f" [{'/'.join(map(str, p.dims))}-D only]"
            lines.append(f"    {p.name} ({p.unit}, bounds {p.bounds}){only}: {p.doc}; random: {p.typical}")
    return "\n".join(lines)

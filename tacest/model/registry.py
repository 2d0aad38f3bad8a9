"""The one registry of effects, 2-D and 3-D: name -> plug-in object, in canonical order.

The order is the order of everything an effect adds: its parameters in theta, its
state rows, the calls of its hooks within a sample (tacest.model.effect).  SPEC's
effect names are all here: ``kind`` says whether the effect is modelled inside the NLP
(``model``) or is a change of the data that the diagnosis fits outside it
(``transform``: latency, time_scale; tacest.diagnosis.transforms).  ``edge_radius`` and
``ground_offset`` are tacest's extensions (3-D, docs/effects.md).
"""

from __future__ import annotations

from tacest.errors import TacestError
from tacest.model.effect import Effect
from tacest.model.effects_body import AngularDamping, ComOffset, LinearDrag
from tacest.model.effects_contact import EdgeRadius, FaceFriction, GroundOffset, Restitution, SoftContact
from tacest.model.effects_sensor import ForceBias, ForceScale


class Latency(Effect):
    """The tactile streams delayed by whole samples (a change of the data)."""

    name = "latency"
    dims = (2, 3)
    kind = "transform"
    doc = "tactile streams delayed by whole samples"


class TimeScale(Effect):
    """The clock (or the length scale) off by a few percent (a change of the data)."""

    name = "time_scale"
    dims = (2, 3)
    kind = "transform"
    doc = "clock or length scale off by a few percent"


#: name -> effect, in canonical order
REGISTRY: dict = {e.name: e for e in (
    Restitution(), AngularDamping(), LinearDrag(), SoftContact(), ForceBias(), ForceScale(), FaceFriction(),
    ComOffset(), GroundOffset(), EdgeRadius(), Latency(), TimeScale())}

#: the name of "no unmodelled effect" (SPEC)
NONE = "none"


def model_effect_names(dim: int) -> tuple:
    """Names of the effects modelled inside the NLP of ``dim`` dimensions, canonical order."""
    return tuple(n for n, e in REGISTRY.items() if e.kind == "model" and dim in e.dims)


def resolve(names, dim: int) -> tuple:
    """The effects named (a name, or an iterable of names; ``none`` and empty names are
    skipped) as a tuple of Effect objects in canonical order, no repeats; a TacestError
    (one line) for an unknown name, a data transform, or an effect not modelled in
    ``dim`` dimensions."""
    if isinstance(names, str):
        names = (names,)
    wanted = []
    for n in names or ():
        n = str(n).strip()
        if n in ("", NONE):
            continue
        eff = REGISTRY.get(n)
        valid = ", ".join(model_effect_names(dim))
        if eff is None:
            raise TacestError(f"unknown effect {n!r}; effects modelled in {dim}-D: {valid}")
        if eff.kind != "model":
            raise TacestError(f"effect {n!r} is not modelled inside the estimator's NLP (it is a data "
                              f"transform); NLP effects: {valid}")
        if dim not in eff.dims:
            raise TacestError(f"effect {n!r} is not modelled in {dim}-D; effects modelled in {dim}-D: {valid}")
        if n not in wanted:
            wanted.append(n)
    return tuple(e for n, e in REGISTRY.items() if n in wanted)


def names_of(effects) -> tuple:
    """The names of a tuple of Effect objects."""
    return tuple(e.name for e in effects)

"""The interface of an effect: a few extra parameters (and per-sample states) that the
model gains when the effect is included, and the terms they add.

An effect is a plug-in object.  The stage models (``tacest.model.stage2d``,
``tacest.model.stage3d``) call its hooks at fixed points of one sample's physics, in
the registry's order (``tacest.model.registry``); an effect that does not act at a point
leaves the default, which changes nothing.  Everything an effect is — its parameters with
units, priors and bounds, its states, its hooks, how its values are reported — lives in
its one class, so that adding an effect touches one module and the registry.

Parameters are held scaled (O(1)) in the NLP: ``physical = scaled × unit(scales)`` for
a linear parameter; a parameter may override the map (:meth:`Effect.report`).  Reported
names are ``"<effect>.<parameter>"`` (estimate ``/params`` attrs, information rows).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from tacest.constants import STANDARD_GRAVITY


@dataclass(frozen=True)
class Scales:
    """The problem's units: L (m) length scale, m0 (kg) mass scale, g (m/s²) gravity
    magnitude (the runs'; standard gravity by default).  Forces are in units of m0·g,
    impulses of m0·g·dt."""

    L: float
    m0: float
    g: float = STANDARD_GRAVITY


@dataclass(frozen=True)
class EffectParameter:
    """One scaled parameter of an effect.

    name : short name (``e``, ``compliance``); centre, sigma : Gaussian prior (scaled
    units), centred on "no effect"; lower, upper : hard bounds (scaled); start : where a
    fit from the estimator's own start begins it (None: at the prior centre); unit :
    physical unit of the reported value; per_unit : ``per_unit(scales)`` -> physical value
    of one scaled unit (linear parameters); doc : one line for the docs."""

    name: str
    centre: float
    sigma: float
    lower: float
    upper: float
    start: Optional[float] = None
    unit: str = "1"
    per_unit: Callable[[Scales], float] = field(default=lambda sc: 1.0, compare=False)
    doc: str = ""


class Effect:
    """Base class of every effect: defaults that change nothing.

    Class attributes: ``name`` (SPEC effect name, or a documented tacest extension),
    ``dims`` (world dimensions it is modelled in), ``kind`` (``"model"``: extra
    parameters inside the NLP; ``"transform"``: a change of the data, fitted outside the
    NLP, see tacest.diagnosis.transforms), ``doc`` (one line).
    """

    name: str = ""
    dims: tuple = ()
    kind: str = "model"
    doc: str = ""

    # -- parameters and states ------------------------------------------------------
    def parameters(self, K: int, dim: int) -> tuple:
        """(EffectParameter, ...) of a shape with K vertices in ``dim`` dimensions."""
        return ()

    def prior(self, par: EffectParameter, config, L: float) -> tuple:
        """(centre, sigma) of a parameter's prior in scaled units; the default is the
        parameter's own.  ``config`` is the estimator's configuration, L the length scale
        (an effect whose prior the user sets in metres converts here)."""
        return par.centre, par.sigma

    def bounds(self, par: EffectParameter, config, L: float, shape_lower) -> tuple:
        """(lower, upper) scaled bounds of a parameter; shape_lower : the shape block's
        lower bounds (scaled), for bounds relative to the smallest extent."""
        return par.lower, par.upper

    def state_rows(self, K: int, dim: int) -> int:
        """Per-sample state rows the effect adds (0: none)."""
        return 0

    def state_lower(self) -> float:
        """Lower bound of every state row (scaled; -inf: free)."""
        return -np.inf

    # -- reporting in physical units ------------------------------------------------
    def report(self, u: dict, sc: Scales, K: int, mu_ground: float) -> dict:
        """{estimate /params name: physical value} from the scaled values ``u``
        ({parameter name: value}); default: each linear parameter times its unit."""
        pars = {p.name: p for dim in self.dims for p in self.parameters(K, dim)}
        return {f"{self.name}.{n}": float(v) * pars[n].per_unit(sc) for n, v in u.items()}

    def scaled(self, params: dict, sc: Scales, K: int, mu_ground: float, dim: int) -> dict:
        """The inverse of :meth:`report`: {parameter name: scaled value} from an
        estimate's /params; KeyError naming the missing /params entry."""
        out = {}
        for p in self.parameters(K, dim):
            key = f"{self.name}.{p.name}"
            if key not in params:
                raise KeyError(key)
            out[p.name] = float(params[key]) / p.per_unit(sc)
        return out

    def info_name(self, par: EffectParameter) -> str:
        """Row name of a parameter in the information matrix."""
        return f"{self.name}.{par.name}"

    def info_factor(self, par: EffectParameter, u: float, sc: Scales) -> float:
        """d(scaled) / d(physical) of a parameter at scaled value u (I_phys = D I D)."""
        return 1.0 / par.per_unit(sc)

    # -- hooks of both dimensions ---------------------------------------------------
    def physics_gain(self, u: dict):
        """A factor on every force and mass the physics residuals see, or None."""
        return None

    def sensor_gain(self, u: dict):
        """A factor on the force the sensor reads (reading = gain × force + bias), or None."""
        return None

    def sensor_bias(self, u: dict, ctx):
        """An offset (D,) N on the force the sensor reads (ctx.m0 kg, ctx.grav m/s²), or None."""
        return None

    # -- 2-D model hooks (tacest.model.stage2d; see Stage2DContext) --------------------
    def body_vertices_2d(self, V, u: dict, L):
        """Vertices (K, 2) m of the body frame (origin at the COM) from the shape's."""
        return V


    def ground_surface_2d(self, ctx) -> None:
        """Move the ground the contact laws see (ctx.phi_c, ctx.vn_c; rows in
        ctx.dynamics_rows)."""

    def ground_friction_2d(self, ctx) -> None:
        """Change the ground friction coefficient ctx.mu_g."""

    def impacts_2d(self, ctx) -> None:
        """Change the contact laws at impacts (ctx.phi_c, ctx.vn_c, ctx.impulse_levers)."""


    def body_impulse_2d(self, ctx):
        """An extra generalized impulse (3,) over the interval [N·s, N·s, N·m·s], or None."""
        return None

    def start_2d(self, ctx) -> None:
        """Terms of a run's first sample (ctx.phi, ctx.rest_rows)."""

    def initial_states_2d(self, u: dict, mass_ratio: float, LG_normal, K: int):
        """(rows, T) start values of the effect's states under ground impulses LG_normal
        (K, T-1) (scaled), or None for zeros."""
        return None

    #: a stage output from which the effect's states are set sample by sample before an
    #: impulse stage (tacest.model.stage2d.StageModel2D.settle_states), or None
    settled_output: Optional[str] = None

    # -- 3-D model hooks (tacest.model.stage3d; see Stage3DContext) --------------------
    #: poses before t-2 the 3-D stage of the interval (t-1, t] must see for this effect
    #: (0: the stage's three; restitution looks back at the approach before an impact)
    history_3d: int = 0

    def impacts_3d(self, ctx) -> None:
        """Change the contact laws at impacts (ctx.phi, ctx.impulse_R; law rows in
        ctx.dynamics_rows), from the earlier poses and velocities (ctx.past)."""

    def com_shift_3d(self, u: dict, L):
        """(3,) m: where the centre of mass lies in the shape's own frame (its centroid at
        the origin), or None.  The body frame's origin is the COM: shape points move by
        minus this."""
        return None

    def body_impulse_3d(self, ctx):
        """An extra impulse over the interval: (linear (3,) N·s world frame, angular (3,)
        N·m·s body frame), or None."""
        return None

    def ground_friction_3d(self, ctx) -> None:
        """Change the ground friction coefficient ctx.mu_g (R body-to-world, n_g)."""

    def ground_surface_3d(self, ctx) -> None:
        """Move the ground the contact laws see: ctx.phi (K gaps, m) from the normal ground
        impulses ctx.lam_n (K, units of m0·g·dt)."""

    def ground_height_3d(self, u: dict, L):
        """Height (m) of the ground plane above the run's /scene ground_height, or None."""
        return None

    def rounding_3d(self, u: dict, L):
        """Radius (m) of rounded edges and corners of a box, or None."""
        return None

    def __repr__(self):
        return f"<effect {self.name}>"


def physics_gain(effects, u: dict):
    """The factor on every force and mass the physics residuals see: the product of the
    effects' :meth:`Effect.physics_gain` (force_scale), 1.0 when none has one.  u :
    {effect name: {parameter: value}}."""
    gain = 1.0
    for e in effects:
        factor = e.physics_gain(u[e.name])
        if factor is not None:
            gain = factor if isinstance(gain, float) else gain * factor
    return gain


def sensor_reading(effects, ctx, force):
    """The force sensor's reading (D,) N of a model force (D,) N: every effect's gain, then
    every effect's bias (force_scale, force_bias; the plain model reads the force itself).
    ctx : the stage's context (u, m0, grav)."""
    for e in effects:
        gain = e.sensor_gain(ctx.u[e.name])
        if gain is not None:
            force = gain * force
    for e in effects:
        bias = e.sensor_bias(ctx.u[e.name], ctx)
        if bias is not None:
            force = force + bias
    return force


def parameter_table(effects, K: int, dim: int) -> list:
    """[(effect, EffectParameter)] of the effect block, in the order of ``effects``."""
    return [(e, p) for e in effects for p in e.parameters(K, dim)]

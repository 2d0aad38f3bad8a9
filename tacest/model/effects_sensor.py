"""Effects of the force sensor: force_bias and force_scale (2-D and 3-D)."""

from __future__ import annotations

import casadi as ca
import numpy as np

from tacest.model.effect import Effect, EffectParameter


#: world axes of a force bias's components
_AXES = ("x", "y", "z")


class ForceBias(Effect):
    """A constant offset (fx, fy[, fz]) on every measured force sample, units of m0·g (N)."""

    name = "force_bias"
    dims = (2, 3)
    doc = "constant offset on the measured force"

    def parameters(self, K, dim):
        return tuple(EffectParameter(f"f{a}", 0.0, 1.0, -10.0, 10.0, unit="N", per_unit=lambda sc: sc.m0 * sc.g,
                                     doc=f"offset along world {a}") for a in _AXES[:dim])

    def sensor_bias(self, u, ctx):
        return ca.vertcat(*(u[f"f{a}"] for a in _AXES if f"f{a}" in u)) * ctx.m0 * ctx.grav


class ForceScale(Effect):
    """A wrong force-sensor gain: measured force = exp(log_gain) × model force.

    The physics residuals (dynamics, complementarity, cone, dissipation, Occam) see the
    model's forces and mass in the sensor's units (× gain), as the force residual does.
    Then (mass, impulses, gain) and (mass/c, impulses/c, gain·c) are the same model, as
    they are the same data: without the factor a gain above 1 let the fit shrink every
    force and the mass, and with them every physics residual, for free (a clean
    recording's gain went to 5.9).  Only a mass known from elsewhere (a mass prior)
    splits gain and mass."""

    name = "force_scale"
    dims = (2, 3)
    doc = "wrong force-sensor gain"

    def parameters(self, K, dim):
        return (EffectParameter("log_gain", 0.0, 0.5, float(np.log(0.1)), float(np.log(10.0)),
                                doc="log of the sensor's gain"),)

    def report(self, u, sc, K, mu_ground):
        return {"force_scale.gain": float(np.exp(u["log_gain"]))}

    def scaled(self, params, sc, K, mu_ground, dim):
        if "force_scale.gain" not in params:
            raise KeyError("force_scale.gain")
        return {"log_gain": float(np.log(float(params["force_scale.gain"])))}

    def info_name(self, par):
        return "force_scale.gain"

    def info_factor(self, par, u, sc):
        return 1.0 / float(np.exp(u))  # d log(gain) / d gain

    def physics_gain(self, u):
        return ca.exp(u["log_gain"])

    def sensor_gain(self, u):
        return ca.exp(u["log_gain"])

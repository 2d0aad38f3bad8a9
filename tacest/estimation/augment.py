"""Effect parameters of the NLP augmentations (problem.NLP_EFFECTS) in physical units.

The NLP holds each effect parameter scaled (O(1), see problem.NLP_EFFECTS); this module
converts between the scaled values u and what an estimate file reports:

==========================  =========================================  =============================
estimate ``/params`` name   physical value                             information row (unit)
==========================  =========================================  =============================
``restitution.e``           e = u                                      ``restitution.e`` (1)
``angular_damping.c``       c = u · m0 · L² (N·m·s)                    ``angular_damping.c``
``linear_drag.b``           b = u · m0 (N·s/m)                         ``linear_drag.b``
``soft_contact.compliance`` C = u · COMPLIANCE_UNIT · L / (m0 g) (m/N)  ``soft_contact.compliance``
``soft_contact.stiffness``  1 / C (N/m; inf without compliance)        (none: 1/C is not linear)
``soft_contact.tau``        tau = u · TAU_UNIT (s; damping / stiffness)  ``soft_contact.tau``
``soft_contact.damping``    tau / C (N·s/m; inf without compliance)     (none: not linear)
``force_bias.fx``, ``fy``   u · m0 · g (N)                             ``force_bias.fx``, ``.fy``
``force_scale.gain``        exp(u)                                     ``force_scale.gain`` (1)
``face_friction.values``    friction_ground + d_i, one per face        ``face_friction.d<i>`` (1)
``com_offset.dx``, ``dy``   u · L (m, body axes)                       ``com_offset.dx``, ``.dy``
==========================  =========================================  =============================

m0 (kg) and L (m) are the problem's scales (estimate attrs ``mass_scale``,
``length_scale``); g = 9.81 m/s².
"""

from __future__ import annotations

import numpy as np

from tacest.errors import TacestError
from tacest.estimation.problem import COMPLIANCE_UNIT, PHYS_NAMES, TAU_UNIT, effect_parameters

GRAVITY = 9.81


def _unit(key: str, L: float, m0: float) -> float:
    """Physical value per scaled unit of the (linear) effect parameter ``key``."""
    name = key.split(".", 1)[1]
    return {
        "fx": m0 * GRAVITY, "fy": m0 * GRAVITY,
        "b": m0, "c": m0 * L * L,
        "compliance": COMPLIANCE_UNIT * L / (m0 * GRAVITY), "tau": TAU_UNIT,
        "dx": L, "dy": L,
    }.get(name, 1.0)


def effect_info_names(problem) -> list:
    """Information-matrix row names of the effect block, in theta order."""
    return [("force_scale.gain" if k == "force_scale.log_gain" else k) for k in problem.eff_index]


def effect_info_factors(problem, theta, L: float, m0: float) -> np.ndarray:
    """d(u)/d(physical) per effect parameter (n_eff,), to turn the scaled information
    into the physical one (I_phys = D I D)."""
    a = problem.n_shape + len(PHYS_NAMES)
    d = np.ones(problem.n_eff)
    for k, j in problem.eff_index.items():
        if k == "force_scale.log_gain":
            d[j] = 1.0 / float(np.exp(theta[a + j]))  # d log(gain) / d gain
        else:
            d[j] = 1.0 / _unit(k, L, m0)
    return d


def effect_params(problem, theta, L: float, m0: float) -> dict:
    """{estimate /params name: physical value} of the effect block of theta (scaled)."""
    a = problem.n_shape + len(PHYS_NAMES)
    u = {k: float(theta[a + j]) for k, j in problem.eff_index.items()}
    out = {}
    for k, val in u.items():
        eff, name = k.split(".", 1)
        if k == "force_scale.log_gain":
            out["force_scale.gain"] = float(np.exp(val))
        elif eff == "face_friction":
            continue
        elif k == "soft_contact.compliance":
            c = val * _unit(k, L, m0)
            out[k] = c
            out["soft_contact.stiffness"] = 1.0 / c if c > 0 else float("inf")
        elif k == "soft_contact.tau":
            tau = val * _unit(k, L, m0)
            c = u["soft_contact.compliance"] * _unit("soft_contact.compliance", L, m0)
            out[k] = tau
            out["soft_contact.damping"] = tau / c if c > 0 else float("inf")
        else:
            out[k] = val * _unit(k, L, m0)
    if "face_friction" in problem.effects:
        mu_g = float(theta[problem.n_shape + 2])
        out["face_friction.values"] = np.array([mu_g + u[f"face_friction.d{i}"] for i in range(problem.K)])
    return out


def effect_theta(effects, n_vertices: int, params: dict, L: float, m0: float, friction_ground: float) -> np.ndarray:
    """Scaled effect block (n_eff,) of the NLP with ``effects`` on a shape of
    ``n_vertices`` vertices (problem.effect_parameters order) from an estimate's
    /params (the inverse of effect_params); a TacestError naming the missing parameter."""
    K = int(n_vertices)
    rows = effect_parameters(tuple(effects), K)
    u = np.zeros(len(rows))
    for j, (eff, name, *_) in enumerate(rows):
        k = f"{eff}.{name}"
        if k == "force_scale.log_gain":
            key = "force_scale.gain"
        elif eff == "face_friction":
            key = "face_friction.values"
        else:
            key = k
        if key not in params:
            raise TacestError(f"the fixed estimate has no parameter {key!r} (its model: effect {eff} missing)")
        v = params[key]
        if k == "force_scale.log_gain":
            u[j] = np.log(float(v))
        elif eff == "face_friction":
            vals = np.asarray(v, float).reshape(-1)
            if vals.size != K:
                raise TacestError(f"the fixed estimate's face_friction.values has {vals.size} entries, "
                                  f"the shape has {K} faces")
            u[j] = vals[int(name[1:])] - friction_ground
        else:
            u[j] = float(v) / _unit(k, L, m0)
    return u

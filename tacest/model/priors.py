"""The estimators' weak parameter priors: the fixed head of every prior vector, and the
friction prior (one definition for 2-D, 3-D, the shooting method and planning).

The prior vector of a problem starts with :data:`PRIOR_HEAD` (:func:`prior_head` of the
configuration's ``[prior]``), then the effects' (centre, sigma) pairs and the shape's
reference; the stage models read it by these names' positions.

**Friction** (``[prior] friction``, ``friction_sigma``, ``friction_log_sigma``): with
``friction_log_sigma`` > 0 a log-normal prior of median ``friction``,
r = (ln μ − ln friction) / friction_log_sigma; with 0 a normal one,
r = (μ − friction) / friction_sigma.  The log-normal prior is the default: a coefficient
of friction between an object and a table or a fingertip lies between about 0.1 and 1.5,
and μ → 0 is not "as likely as 0.5".  Without a force stream the touches alone say
little about friction, and a fit could follow them with a frictionless ground that lets
the object drift wherever the touches need it (a wrong shape that moves more: 2-D boxes
30 mm off at μ = 0.01, the bound, docs/estimation.md, "Friction prior"); the normal
prior (σ 1) charged 0.1 objective units for that, the log-normal one (σ_log 0.7)
charges 15.
"""

from __future__ import annotations

import numpy as np

#: the fixed head of every prior vector, in order ("on" multiplies the whole prior: 0 in
#: a model that holds the parameters it would act on)
PRIOR_HEAD = ("mass_log_sigma", "inertia_log_sigma", "friction", "friction_sigma", "shape_sigma", "on",
              "friction_log_sigma")
N_PRIOR_FIXED = len(PRIOR_HEAD)
#: positions in the head
MASS_LOG_SIGMA, INERTIA_LOG_SIGMA, FRICTION, FRICTION_SIGMA, SHAPE_SIGMA, ON, FRICTION_LOG_SIGMA = range(N_PRIOR_FIXED)
#: smallest friction the log-normal residual takes the log of (the estimators' bounds
#: keep μ >= 0.01; this only keeps a stray evaluation finite)
MU_FLOOR = 1e-6


def prior_head(prior) -> np.ndarray:
    """(N_PRIOR_FIXED,) the head of the prior vector from a configuration's ``[prior]``
    (tacest.estimation.config.Prior)."""
    values = {**{n: getattr(prior, n) for n in PRIOR_HEAD if n != "on"}, "on": 1.0}
    return np.array([float(values[n]) for n in PRIOR_HEAD], float)


def friction_residual(mu, head):
    """Whitened residual of a friction coefficient under the prior head (CasADi SX/MX or
    float; head indexable by the positions above): log-normal where
    ``friction_log_sigma`` > 0, else normal (module docstring)."""
    import casadi as ca

    log_sigma = head[FRICTION_LOG_SIGMA]
    lognormal = (ca.log(ca.fmax(mu, MU_FLOOR)) - ca.log(head[FRICTION])) / ca.fmax(log_sigma, 1e-12)
    normal = (mu - head[FRICTION]) / head[FRICTION_SIGMA]
    return ca.if_else(log_sigma > 0, lognormal, normal)


def parameter_prior_residual(log_mass, inertia_offset, mu_ground, mu_finger, shape_offset, head):
    """Whitened residuals (CasADi) of the physical parameters' priors under the prior head,
    in the order every problem stacks them: log(m/m0) / mass_log_sigma, the inertia's
    offset from its uniform-density value (2-D: log ratio, 3-D: log-Cholesky factor) /
    inertia_log_sigma, both frictions (:func:`friction_residual`), the shape's offset from
    its reference / shape_sigma."""
    import casadi as ca

    return ca.vertcat(log_mass / head[MASS_LOG_SIGMA], inertia_offset / head[INERTIA_LOG_SIGMA],
                      friction_residual(mu_ground, head), friction_residual(mu_finger, head),
                      shape_offset / head[SHAPE_SIGMA])


def friction_information(mu: float, prior) -> float:
    """The prior's Gauss–Newton information of one friction coefficient at μ (its
    residual's squared derivative): 1/friction_sigma² (normal) or
    1/(μ·friction_log_sigma)² (log-normal); ``prior`` a configuration's ``[prior]``."""
    if prior.friction_log_sigma > 0:
        return 1.0 / (max(float(mu), MU_FLOOR) * prior.friction_log_sigma) ** 2
    return 1.0 / prior.friction_sigma ** 2

"""Per-sample linearizations of the 2-D stage model: one interval's whitened residuals
and their Jacobian with respect to its local variables, for the observed information of
a fit (tacest.estimation.uncertainty) and the expected information of a planned action
(tacest.information.expected).

The kinematic equality constraints (eq. D2) enter as residuals with a tight sigma
(:data:`KINEMATICS_SIGMA`), their Gauss–Newton stand-in.

Active-set rows.  The estimator's contact laws are relaxed for the solver's sake: a
loaded vertex may sit within a fraction of a millimetre of the ground at small cost, and
the maximal-dissipation residual is flat to second order at zero slip (its gradient is
the friction impulse times the slip).  Linearized there, a resting object is free to
drift and tilt: on a box at rest after three pokes the final position came out uncertain
by 4-15 cm, so that every new poke looked as if it first had to find the object again,
and a touch on an untouched face taught no more than one on a known face.  The
information is therefore taken on the active set of the fit, as for constrained
estimation: at every interval, a ground vertex that carries load (normal impulse at least
:data:`ACTIVE_LOAD_FRACTION` of the object's weight) adds the row gap / sigma_pen (it is
on the ground, to the tolerated penetration), and one that also sticks (slip below the
estimator's slip smoothing SLIP_EPS, friction inside :data:`ACTIVE_CONE_FRACTION` of the
cone) adds slip / SLIP_EPS (it does not move).  The rows carry no weight where the
contact is open or sliding, so sliding and lift-off stay as the relaxed laws describe
them.  Their weights are fixed at the linearization point (:func:`active_weights`).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from tacest.dynamics.laws import SLIP_EPS
from tacest.model.stage2d import (G, SQUARED_TERMS, START_TERM_OUTPUTS, TERMS, start_local_variables,
                                  stage_local_variables)

#: scaled units (L per second) of the stand-in residual for eq. D2; 1e-4 is far tighter
#: than any measurement, so it acts as the constraint without dominating the conditioning
KINEMATICS_SIGMA = 1e-4


#: a ground vertex is in the active set when its normal impulse is at least this
#: fraction of the object's weight per interval (a box resting on two vertices carries
#: half on each; a vertex grazing the ground while the object tips carries little)
ACTIVE_LOAD_FRACTION = 0.05
#: ... and sticks when its friction impulse is inside this fraction of the cone (at the
#: cone's edge it is about to slide, which the dissipation residual describes)
ACTIVE_CONE_FRACTION = 0.95


def active_weights(phi, slip, lam_n, lam_t, mu, weight, sig_pen):
    """(2K, N) weights of the active-set rows (module docstring) of N intervals.

    phi, slip : (K, N) ground gaps (m) and slip velocities (m/s); lam_n, lam_t : (K, N)
    normal and tangential ground impulses (units of the reference weight m0·g·dt);
    mu : (N,) ground friction; weight : (N,) the object's weight in those units;
    sig_pen : (N,) m, the tolerated penetration.  Rows [gap weights (1/m); slip weights
    (s/m)]; 0 where the vertex is not loaded, or (slip rows) not sticking.
    """
    loaded = lam_n >= ACTIVE_LOAD_FRACTION * np.asarray(weight)[None, :]
    stick = loaded & (np.abs(slip) <= SLIP_EPS) & (np.abs(lam_t) <= ACTIVE_CONE_FRACTION * np.asarray(mu)[None, :] * lam_n)
    return np.concatenate([loaded / np.asarray(sig_pen)[None, :], stick / SLIP_EPS], axis=0)


def contact_state_function(stage):
    """SX Function (the stage's inputs) -> (phi (K,) m, slip (K,) m/s, mu, weight): what
    :func:`active_weights` needs besides the impulses."""
    ins = stage.sx_in()
    out = dict(zip(stage.name_out(), stage(*ins)))
    return ca.Function("contact_state", list(ins), [out["phi_ground"], out["slip_ground"], out["mu_ground"],
                                                    out["weight"]])


def stage_active_weights(cstate, N, args, n_k):
    """(2K, N) :func:`active_weights` of N intervals from the mapped contact-state
    function ``cstate`` (a callable of the stage's 9 inputs returning (phi, slip, mu,
    weight) as (K, N), (K, N), (1, N), (1, N) arrays); args : the stage's inputs with
    the ground impulses (2K, N) at index 4 and the global vector g at index 8."""
    phi, slip, mu, weight = (np.asarray(a, float) for a in cstate(*args))
    lg = np.asarray(args[4], float).reshape(2 * n_k, N)
    g = np.asarray(args[8], float)
    sig_pen = g[G["sig_pen"]] if g.ndim == 1 else g[G["sig_pen"], :]
    return active_weights(phi.reshape(n_k, N), slip.reshape(n_k, N), lg[:n_k], lg[n_k:], mu.reshape(N),
                          weight.reshape(N), np.broadcast_to(sig_pen, (N,)))


def stage_residual_jacobian(stage):
    """SX Function (the stage's inputs, w, a) -> (r, J): one interval's whitened
    residuals (each squared term times sqrt of its weight, then eq. D2 over
    KINEMATICS_SIGMA, then the active-set rows a ⊙ [gaps; slips] with a from
    :func:`active_weights`) and their dense Jacobian with respect to the interval's
    local variables y (stage2d.stage_local_variables: [q_prev, v_prev, q, v,
    lam_ground, lam_finger, phys, s_prev, s])."""
    ins = stage.sx_in()
    w = ca.SX.sym("w", len(TERMS))
    out = dict(zip(stage.name_out(), stage(*ins)))
    K = out["phi_ground"].shape[0]
    a = ca.SX.sym("a", 2 * K)
    r = ca.vertcat(*[ca.sqrt(w[TERMS.index(t)]) * ca.vec(out[t]) for t in SQUARED_TERMS],
                   out["g_kin"] / KINEMATICS_SIGMA,
                   a * ca.vertcat(out["phi_ground"], out["slip_ground"]))
    y = stage_local_variables(ins)
    return ca.Function("stage_rj", [*ins, w, a], [ca.densify(r), ca.densify(ca.jacobian(r, y))])


def start_residual_jacobian(start):
    """SX Function (the start function's inputs, w) -> (r, J): a run's first-sample
    whitened residuals (START_TERM_OUTPUTS) and their dense Jacobian with respect to its
    local variables [q, v, phys, s] (stage2d.start_local_variables)."""
    ins = start.sx_in()
    w = ca.SX.sym("w", len(TERMS))
    out0 = dict(zip(start.name_out(), start(*ins)))
    r0 = ca.vertcat(*[ca.sqrt(w[TERMS.index(t)]) * ca.vec(out0[name]) for t, name in START_TERM_OUTPUTS])
    return ca.Function("start_rj", [*ins, w],
                       [ca.densify(r0), ca.densify(ca.jacobian(r0, start_local_variables(ins)))])

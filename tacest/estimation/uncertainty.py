"""Observed (Gauss–Newton) information of a fit's parameters, and their standard
deviations: one construction for 2-D and 3-D.

With r(z) the stacked whitened residuals (each term times sqrt of its weight) and J its
Jacobian with respect to the free decision variables z = (theta, states, impulses),
the observed information is I = Jᵀ J.  The states and impulses are nuisance variables:
the information of theta (and, in 2-D, the final pose of the last run) is the Schur
complement

    I_θ = I_θθ - I_θx (I_xx + δ I)⁻¹ I_xθ,

with the nuisance columns scaled to unit norm first (I_xx then has a unit diagonal) and
δ a tiny ridge on that scaled block, for directions the squared residuals do not see
(e.g. impulse splits among ground vertices that only the complementarity penalties
decide); see :func:`schur_information`.  In 2-D the kinematic constraints (eq. D2) and
the active-set rows of the fit enter as residuals (tacest.model.jacobians2d), and the
lifted physical quantities ``phys`` are folded into theta by the chain rule,
J_θ ← J_θ + J_phys ∂phys/∂θ (:func:`fold_lifted_parameters`).  In 3-D the kinematics
are eliminated (tacest.estimation.problem3d).

Two standard deviations come out (:class:`Information`): the data's own (``std_data``:
whether the data determine a parameter; infinite where they do not, :func:`std_of`)
and the posterior's (``std``: data and priors, the uncertainty an estimate reports).
Rows are in physical units: lengths m, mass kg, the inertia parameters as their
dimension's (2-D: log ratio to the uniform-density value; 3-D: log-Cholesky of I/m),
friction dimensionless, effect parameters as their effect reports them
(tacest.model.effect), 2-D final pose m / rad.  Held variables (pinned, fixed) get zero
information and infinite std.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from tacest.estimation.solver import held
from tacest.model.effect import Scales

#: ridge on the nuisance block after its columns are scaled to unit norm (unit
#: diagonal).  The block mixes rows of very different weights (eq. D2 over
#: KINEMATICS_SIGMA: entries ~1e4; ground-impulse splits seen only through the
#: complementarity penalties: ~1e-3), so a ridge relative to its largest entry (the
#: earlier 1e-10 · max diag ~ 1e-2) pinned the weakly seen nuisance directions and
#: leaked spurious information into theta: after one press from above, a box's width
#: came out known to 0.8 mm when the objective's profile over the width is flat
#: (4.89 to 5.10 from 44 to 160 mm wide).  On the unit diagonal, 1e-12 and 1e-14 give
#: the same sigmas to 2 % there (width 0.14 m), so 1e-12 is below every direction the
#: data see and well above rounding
RIDGE = 1e-12
#: relative eigenvalue of the information scaled to a unit diagonal (D^-1/2 I D^-1/2,
#: unit-free) at or below which a direction counts as flat, undetermined by the data: a
#: condition number of 1e10, far beyond what a fit's data resolve (finite differences
#: and IPOPT's tolerances give 1e-6..1e-8)
FLAT_RCOND = 1e-10
#: loading (of the unit-norm eigenvector, scaled units) of a parameter on flat
#: directions above which its std is infinite: along a flat direction it would have at
#: least FLAT_LOADING / sqrt(FLAT_RCOND) = 100 times the std it has with the others
#: held, i.e. the data do not determine it.  A parameter outside the flat directions
#: loads on them by rounding only (1e-8 and below)
FLAT_LOADING = 1e-3


@dataclass
class Information:
    """The information of a fit.  matrix (n, n) : the data's, physical units; names (n,);
    std_data {name: sigma} : the data's own (inf where they do not determine it); std
    {name: sigma} : the posterior's (data and priors); shift {name: value} : how far the
    data alone would move each parameter without the penalty (Occam) terms (2-D
    pose-observed fits; empty otherwise); cov (n, n) : the posterior's covariance,
    physical units (NaN in held rows and columns), or None."""

    matrix: Optional[np.ndarray]
    names: list
    std_data: dict
    std: dict
    shift: dict = field(default_factory=dict)
    cov: Optional[np.ndarray] = None


def schur_information(A, B) -> np.ndarray:
    """(n_a, n_a) information of the kept columns with the nuisance ones marginalized:
    AᵀA − AᵀB (BᵀB + δI)⁻¹ BᵀA, computed with B's columns scaled to unit norm (zero
    columns left as they are) and δ = :data:`RIDGE`.

    A : (m, n_a) dense or sparse Jacobian columns of the kept variables;
    B : (m, n_x) sparse Jacobian columns of the nuisance variables.
    """
    return _schur(A, B)[0]


def _schur(A, B, g_a=None, g_b=None):
    """(schur_information(A, B), reduced gradient): with a gradient (g_a (n_a,), g_b
    (n_x,)) of some other function of the same variables, also its gradient with the
    nuisance variables moved along the data's best response, g_a − AᵀB (BᵀB + δI)⁻¹ g_b
    (same scaling and ridge); None without one."""
    A = sp.csc_matrix(A)
    I_aa = (A.T @ A).toarray()
    if B.shape[1] == 0:
        return 0.5 * (I_aa + I_aa.T), (None if g_a is None else np.asarray(g_a, float))
    B = sp.csc_matrix(B)
    norms = np.sqrt(np.asarray(B.multiply(B).sum(axis=0)).ravel())
    norms[norms == 0] = 1.0
    Bs = B @ sp.diags(1.0 / norms)
    I_xx = (Bs.T @ Bs).tocsc()
    I_xa = (Bs.T @ A).toarray()
    lu = spla.splu((I_xx + RIDGE * sp.identity(I_xx.shape[0], format="csc")).tocsc())
    I_s = I_aa - I_xa.T @ lu.solve(I_xa)
    g_r = None
    if g_a is not None:
        g_r = np.asarray(g_a, float) - I_xa.T @ lu.solve(np.asarray(g_b, float) / norms)
    return 0.5 * (I_s + I_s.T), g_r


def std_of(I_phys, free, names):
    """({name: one-sigma}, cov (n, n)) from an information matrix.

    Over the free rows, the information is scaled to a unit diagonal and split into its
    eigen-directions: cov is the pseudo-inverse that drops the flat ones (eigenvalue at
    or below FLAT_RCOND of the largest; NaN outside the free block), and a parameter
    that loads on a flat direction (by more than FLAT_LOADING) gets an infinite std, as
    one without information or held does.  (A plain pseudo-inverse drops the flat
    directions silently and reports such a parameter with the small std it has with the
    others held, e.g. force_scale's gain against the mass.)  Where the eigen-solver
    fails: every std NaN and cov None."""
    n = len(names)
    cov = np.full_like(I_phys, np.nan)
    var = np.full(n, np.inf)
    idx = np.nonzero(free)[0]
    A = I_phys[np.ix_(idx, idx)]
    diag = np.diag(A).copy()
    has = diag > 0
    scale = np.sqrt(np.where(has, diag, 1.0))
    S = A / np.outer(scale, scale)
    S[~has, :] = 0.0
    S[:, ~has] = 0.0
    try:
        w, U = np.linalg.eigh(0.5 * (S + S.T))
    except np.linalg.LinAlgError:
        return {name: float("nan") for name in names}, None
    flat = w <= FLAT_RCOND * max(float(w.max()) if w.size else 0.0, 0.0)
    cov_s = (U[:, ~flat] / w[~flat]) @ U[:, ~flat].T
    cov_f = cov_s / np.outer(scale, scale)
    cov[np.ix_(idx, idx)] = cov_f
    loading = np.sqrt(np.sum(U[:, flat] ** 2, axis=1))
    determined = has & (loading <= FLAT_LOADING) & (np.diag(cov_f) > 0)
    var[idx[determined]] = np.diag(cov_f)[determined]
    std = {name: float(np.sqrt(var[k])) for k, name in enumerate(names)}
    return std, cov


def fold_lifted_parameters(problem, J, z, p):
    """J (m, n_z) sparse with the columns of the lifted ``phys`` block folded into theta's
    (J_θ + J_phys ∂phys/∂θ at z) and zeroed; L and m0 are the first two entries of p."""
    J = sp.csc_matrix(J)
    n_theta, a, n_phys = problem.n_theta, problem.phys_offset, problem.n_phys
    p = np.asarray(p, float).reshape(-1)
    D = np.asarray(problem.phys_jacobian(np.asarray(z, float)[:n_theta], p[0], p[1]))
    J_theta = J[:, :n_theta] + J[:, a: a + n_phys] @ sp.csc_matrix(D)
    return sp.hstack([J_theta, J[:, n_theta:a], sp.csc_matrix((J.shape[0], n_phys)), J[:, a + n_phys:]],
                     format="csc")


def effect_factors(problem, theta, sc: Scales, offset: int) -> np.ndarray:
    """(n_eff,) d(scaled)/d(physical) of every effect parameter at theta (scaled), whose
    effect block starts at ``offset``."""
    return np.array([e.info_factor(p, float(theta[offset + j]), sc) for j, (e, p) in enumerate(problem.effect_params)])


def information_names_2d(problem) -> list:
    """Row names of the 2-D information: the shape's, the physical parameters, the effect
    parameters, the final pose of the last run."""
    shape = problem.shape
    if shape.name == "box":
        shape_names = ["width", "height"]
    else:
        shape_names = [f"vertex{k}_{c}" for k in range(shape.n_vertices) for c in "xy"]
    return shape_names + ["mass", "inertia_log_ratio", "friction_ground", "friction_finger"] \
        + [e.info_name(p) for e, p in problem.effect_params] + ["final_x", "final_y", "final_angle"]


def observed_information_2d(problem, z, p, lbx, ubx, sc: Scales, mass: float, penalty_shift=False) -> Information:
    """The information of a 2-D fit at its solution z (Problem2D, parameter vector p and
    bounds of the final stage; mass kg the fitted mass).  With ``penalty_shift`` (and a
    problem with the Occam term), Information.shift: how far the data alone would move
    each parameter from z, to first order, without the penalty terms of the objective,
    I⁻¹ ∇penalty (the penalty's gradient with the nuisance variables following the
    data, :func:`_schur`).  At the fit the data's and the penalty's gradients cancel: a
    shift of several std says the penalty, not the data, put the parameter where it is."""
    _, J = problem.residual_jacobian(z, p)
    J = J.sparse() if hasattr(J, "sparse") else sp.csc_matrix(np.array(J))
    J = fold_lifted_parameters(problem, sp.csc_matrix(J), z, p)
    n_theta = problem.n_theta
    last = len(problem.structures) - 1
    qa = problem.offsets[last]["Q"][0] + 3 * (problem.structures[last].T - 1)
    keep = list(range(n_theta)) + [qa, qa + 1, qa + 2]
    fixed = held(lbx, ubx)
    is_keep = np.zeros(problem.n_z, bool)
    is_keep[keep] = True
    is_keep[problem.phys_offset: problem.phys_offset + problem.n_phys] = True  # folded into theta, not nuisance
    nuis = np.nonzero(~is_keep & ~fixed)[0]
    g_a = g_b = None
    with_shift = penalty_shift and problem.with_occam
    if with_shift:
        gp = np.asarray(problem.penalty_gradient(z, p), float).reshape(1, -1)
        gp = np.asarray(fold_lifted_parameters(problem, sp.csc_matrix(gp), z, p).todense()).ravel()
        g_a, g_b = gp[keep], gp[nuis]
    I_s, g_r = _schur(J[:, keep], J[:, nuis], g_a, g_b)
    # scaled -> physical units: z_scaled = D · physical  =>  I_phys = D I D
    d = np.ones(len(keep))
    d[: problem.n_shape] = 1.0 / sc.L
    d[problem.n_shape] = 1.0 / mass  # d log m / d m
    d[n_theta: n_theta + 2] = 1.0 / sc.L
    a = n_theta - problem.n_eff
    d[a: n_theta] = effect_factors(problem, np.asarray(z, float)[:n_theta], sc, a)
    prior_H = problem.prior_hessian(np.asarray(z, float)[:n_theta], p)
    names = information_names_2d(problem)
    info = _finish(I_s, d, fixed[keep], names, prior_H, n_theta)
    if penalty_shift:
        info.shift = {name: 0.0 for name in names}
        if with_shift:
            info.shift = {name: float("nan") for name in names}
            free = ~fixed[keep]
            _, cov = std_of(info.matrix, free, names)
            if cov is not None and g_r is not None:
                # in physical units: I_phys = D I_s D, the gradient g_phys = D g_r
                delta = cov[np.ix_(free, free)] @ (d[free] * g_r[free])
                for k, value in zip(np.nonzero(free)[0], delta):
                    info.shift[names[k]] = float(value)
    return info


def information_names_3d(problem) -> list:
    """Row names of the 3-D information: the shape's, mass, the six log-Cholesky inertia
    parameters, the frictions, the effect parameters."""
    from tacest.model.stage3d import PHYS_NAMES_3D

    names = list(problem.shape.param_names)
    for n in PHYS_NAMES_3D:
        names.append("mass" if n == "log_mass" else n)
    return names + [e.info_name(p) for e, p in problem.effect_params]


def observed_information_3d(problem, z, p, lbx, ubx, sc: Scales, mass: float) -> Information:
    """The information of a 3-D fit at its solution z (Problem3D, parameter vector p and
    bounds of the final stage; mass kg the fitted mass).  Priors: their residuals'
    Gauss–Newton information."""
    _, J_all = problem.residual_jacobian(z, p)
    J_all = sp.csc_matrix(J_all.sparse())
    J = J_all[: problem.n_res_data].tocsc()
    n_theta = problem.n_theta
    keep = np.arange(n_theta)
    fixed = held(lbx, ubx)
    is_keep = np.zeros(problem.n_z, bool)
    is_keep[keep] = True
    nuis = np.nonzero(~is_keep & ~fixed)[0]
    I_s = schur_information(J[:, keep], J[:, nuis])
    d = np.ones(n_theta)
    d[: problem.n_shape] = 1.0 / sc.L  # scaled shape = physical / L
    d[problem.n_shape] = 1.0 / mass  # d log m / d m
    a = n_theta - problem.n_eff
    d[a:] = effect_factors(problem, np.asarray(z, float)[:n_theta], sc, a)
    Jp = J_all[problem.n_res_data:, :n_theta].toarray()
    return _finish(I_s, d, fixed[keep], information_names_3d(problem), Jp.T @ Jp, n_theta)


def _finish(I_s, d, kept_fixed, names, prior_H, n_theta) -> Information:
    """Physical units, held rows zeroed, the data's and the posterior's std."""
    I_phys = I_s * np.outer(d, d)
    I_phys[kept_fixed, :] = 0.0
    I_phys[:, kept_fixed] = 0.0
    free = ~kept_fixed
    std_data, _ = std_of(I_phys, free, names)
    # the priors act on theta only; held rows are left out by std_of's free block
    P_phys = np.zeros_like(I_phys)
    P_phys[:n_theta, :n_theta] = np.asarray(prior_H, float) * np.outer(d[:n_theta], d[:n_theta])
    std_post, cov_post = std_of(I_phys + P_phys, free, names)
    return Information(matrix=I_phys, names=names, std_data=std_data, std=std_post, cov=cov_post)


def vertex_jacobian(vertices_of, p_shape) -> np.ndarray:
    """(K·D, n) derivative of the vertices (m, body frame, flattened row by row) by the
    physical shape parameters p_shape (n,) (m), by central differences (step 1e-6 of
    the largest |p|: the vertex maps are smooth and at most quadratic in p, so the
    error is ~1e-12 relative).  vertices_of(p) -> (K, D) m."""
    p = np.asarray(p_shape, float)
    h = 1e-6 * max(float(np.max(np.abs(p))), 1e-3)
    cols = []
    for k in range(p.size):
        e = np.zeros_like(p)
        e[k] = h
        cols.append((np.asarray(vertices_of(p + e), float) - np.asarray(vertices_of(p - e), float)).ravel() / (2 * h))
    return np.column_stack(cols)


def shape_std(J_vertices, cov_shape, dim: int) -> float:
    """RMS over the K vertices of their one-sigma position uncertainty, m:
    sqrt(trace(J C Jᵀ) / K) for J (K·dim, n) (:func:`vertex_jacobian`) and C (n, n) the
    shape parameters' covariance (m²); inf where C has a non-finite entry (a shape
    direction that the data and priors leave undetermined).  A box whose width is known
    to ±2 mm (and its height exactly) has vertices known to ±1 mm: shape_std 1 mm."""
    C = np.asarray(cov_shape, float)
    J = np.asarray(J_vertices, float)
    if C.size == 0:
        return 0.0
    if not np.all(np.isfinite(C)):
        return float("inf")
    n_vertices = J.shape[0] // dim
    return float(np.sqrt(max(float(np.trace(J @ C @ J.T)), 0.0) / n_vertices))

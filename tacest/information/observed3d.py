"""Observed (Gauss–Newton) information of the 3-D estimator's parameters.

The same construction as :mod:`tacest.information.observed` (2-D): I = Jᵀ J of the
stacked whitened data residuals (priors excluded: the matrix says what the DATA tell;
the 3-D problem has no kinematic constraints, they are eliminated, see problem3d.py),
and the poses and impulses eliminated as nuisance variables by the Schur complement

    I_θ = I_θθ - I_θx (I_xx + δ I)⁻¹ I_xθ.

Rows: the shape parameters (m), ``mass`` (kg), the six log-Cholesky inertia parameters
(dimensionless, see :mod:`tacest.dynamics.rigid3d`), ``friction_ground`` and
``friction_finger``.  A fixed parameter (e.g. the mass without a force stream) has zero
information and infinite std: the data cannot tell it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from tacest.estimation.problem3d import PHYS_NAMES_3D
from tacest.information.observed import schur_information


def data_jacobian_3d(problem, z, p):
    """(n_r, n_z) scipy CSC: Jacobian of the stacked whitened data residuals (each term
    times the square root of its weight, the quaternion-norm residuals included; priors
    excluded)."""
    _, J = problem.residual_jacobian(z, p)
    return sp.csc_matrix(J.sparse())[: problem.n_res_data].tocsc()


def information_names_3d(problem):
    names = [f"{n}" for n in problem.shape.param_names]
    for n in PHYS_NAMES_3D:
        names.append("mass" if n == "log_mass" else n)
    return names


def observed_information_3d(problem, z, p, lbx, ubx, L, mass):
    """(I (n, n), names (n,), std {name: sigma}) at the solution z.

    Units: shape parameters in m (their scaled values times L), mass in kg, the rest
    as in theta.  Fixed variables (lbx == ubx) get zero rows and infinite std.
    """
    J = data_jacobian_3d(problem, z, p)
    n_theta = problem.n_theta
    keep = np.arange(n_theta)
    fixed = np.asarray(lbx) == np.asarray(ubx)
    is_keep = np.zeros(problem.n_z, bool)
    is_keep[keep] = True
    nuis = np.nonzero(~is_keep & ~fixed)[0]
    I_s = schur_information(J[:, keep], J[:, nuis])
    d = np.ones(n_theta)
    d[: problem.n_shape] = 1.0 / L  # scaled shape = physical / L
    d[problem.n_shape] = 1.0 / mass  # d log m / d m
    d[problem.theta_index("ground_offset")] = 1.0 / L  # scaled offsets = metres / L
    d[problem.theta_index("edge_radius")] = 1.0 / L
    I_phys = I_s * np.outer(d, d)
    kept_fixed = fixed[keep]
    I_phys[kept_fixed, :] = 0.0
    I_phys[:, kept_fixed] = 0.0
    names = information_names_3d(problem)
    free = ~kept_fixed
    cov = np.full_like(I_phys, np.nan)
    cov[np.ix_(free, free)] = np.linalg.pinv(I_phys[np.ix_(free, free)], rcond=1e-12, hermitian=True)
    std = {name: (float(np.sqrt(cov[k, k])) if free[k] and cov[k, k] > 0 else float("inf"))
           for k, name in enumerate(names)}
    return I_phys, names, std

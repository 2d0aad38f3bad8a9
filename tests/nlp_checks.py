"""Shared numeric checks of the 2-D NLP's derivatives (imported by the test modules)."""

import casadi as ca
import numpy as np

#: central-difference step in scaled units (O(1) values): truncation O(h²·f''') and
#: rounding O(eps·|f|/h) are both ~1e-8 relative at a smooth generic point
FD_STEP = 1e-6
#: relative tolerance of a derivative against its central difference: 1e-5 leaves a wide
#: margin over the ~1e-8 error of FD_STEP
FD_RTOL = 1e-5


def assert_derivatives_match_finite_differences(pr, z, p, f_rounding_margin=0.0, n_random=40, seed=1, extra=()):
    """The objective's gradient and the constraints' Jacobian of Problem2D pr at (z, p)
    match central differences in every parameter coordinate, the coordinates ``extra``
    and n_random other ones.

    f_rounding_margin: multiple of the objective's own rounding, eps·|f| / FD_STEP, added
    to the gradient tolerance (for points where |f| is large)."""
    f = ca.Function("f", [pr.z_sym, pr.p_sym], [pr.f])
    grad = np.asarray(ca.Function("g", [pr.z_sym, pr.p_sym], [ca.gradient(pr.f, pr.z_sym)])(z, p)).ravel()
    gfun = ca.Function("c", [pr.z_sym, pr.p_sym], [pr.g])
    jac = np.asarray(ca.DM(ca.Function("J", [pr.z_sym, pr.p_sym], [ca.jacobian(pr.g, pr.z_sym)])(z, p)))
    rng = np.random.default_rng(seed)
    idx = list(range(pr.n_theta + pr.n_phys)) + list(extra) + rng.choice(pr.n_z, n_random, replace=False).tolist()
    h = FD_STEP
    f0 = abs(float(f(z, p)))
    for i in idx:
        e = np.zeros(pr.n_z)
        e[i] = h
        fd = (float(f(z + e, p)) - float(f(z - e, p))) / (2 * h)
        tol = FD_RTOL * max(1.0, abs(grad[i])) + f_rounding_margin * np.finfo(float).eps * f0 / h
        assert abs(fd - grad[i]) <= tol, (i, fd, grad[i])
        gd = (np.asarray(gfun(z + e, p)).ravel() - np.asarray(gfun(z - e, p)).ravel()) / (2 * h)
        np.testing.assert_allclose(gd, jac[:, i], rtol=FD_RTOL, atol=FD_RTOL)

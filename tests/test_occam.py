"""The Occam term of pose-observed trajectories (problem.pose_occam): the Kalman filter's
steady state it stands for, its derivatives, and what it is for (the marginal
likelihood's estimate of how freely a trajectory moves, where the joint fit collapses)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import scipy.linalg as sl
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from tacest.model.occam import pose_occam

_x = ca.SX.sym("log_lam")
OCCAM = ca.Function("occam", [_x], [pose_occam(_x)])
OCCAM_D1 = ca.Function("d1", [_x], [ca.jacobian(pose_occam(_x), _x)])
OCCAM_D2 = ca.Function("d2", [_x], [ca.hessian(pose_occam(_x), _x)[0]])


def steady_innovation_variance(lam: float) -> float:
    """S / sigma_p² of the steady-state Kalman filter of q_t = q_(t-1) + v_t,
    v_t = v_(t-1) + w_t (w ~ N(0, lam²), units of sigma_p and dt), y_t = q_t + N(0, 1)."""
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = lam**2 * np.array([[1.0, 1.0], [1.0, 1.0]])
    P = sl.solve_discrete_are(F.T, np.array([[1.0], [0.0]]), Q, np.array([[1.0]]))
    return P[0, 0] + 1.0


def test_pose_occam_is_half_the_log_of_the_steady_innovation_variance():
    # 1e-4 .. 1e3 spans heavy bodies (physics far tighter than the data) to light ones;
    # 1e-9: SciPy's Riccati solver is accurate to ~1e-12 relative there, the Newton
    # solution to machine precision
    for lam in np.logspace(-4, 3, 29):
        expected = 0.5 * np.log(steady_innovation_variance(lam))
        assert float(OCCAM(np.log(lam))) == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_pose_occam_asymptotes_and_monotone():
    """≈ (lam / 2)^½ for a heavy body, ≈ log lam for a light one, increasing between."""
    for lam in (1e-8, 1e-7):  # next order: relative lam^½
        assert float(OCCAM(np.log(lam))) == pytest.approx(np.sqrt(lam / 2), rel=1e-3)
    for lam in (1e5, 1e6):
        assert float(OCCAM(np.log(lam))) == pytest.approx(np.log(lam), rel=1e-6)
    ll = np.linspace(np.log(1e-6), np.log(1e4), 200)
    assert np.all(np.diff([float(OCCAM(u)) for u in ll]) > 0)


def test_pose_occam_derivatives_match_finite_differences():
    # h = 1e-3 in log lam: central differences are accurate to ~h² (third or fourth
    # derivative) / 6 < 1e-7, and rounding costs ~1e-15 |f| / h² <= 1e-8
    h = 1e-3
    for u in np.linspace(np.log(1e-6), np.log(1e4), 23):
        f = [float(OCCAM(u + k * h)) for k in (-1, 0, 1)]
        assert float(OCCAM_D1(u)) == pytest.approx((f[2] - f[0]) / (2 * h), rel=1e-6, abs=1e-8)
        assert float(OCCAM_D2(u)) == pytest.approx((f[2] - 2 * f[1] + f[0]) / h**2, rel=1e-5, abs=1e-7)


def _random_walk_fits(seed: int, s_true: float, T: int, grid: np.ndarray):
    """Objective of the joint fit (trajectory and process sd s together, as the NLP fits
    a trajectory and a mass) on a grid of s, without and with the Occam term: a body
    with process sd s_true per sample, observed with unit noise at every sample."""
    rng = np.random.default_rng(seed)
    q = np.cumsum(np.cumsum(rng.normal(size=T) * s_true))
    y = q + rng.normal(size=T)
    D2 = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(T - 2, T))  # velocity changes of q
    joint, with_occam = [], []
    for s in grid:
        qz = spl.spsolve((sp.eye(T) + D2.T @ D2 / s**2).tocsc(), y)  # the best trajectory at s
        j = 0.5 * np.sum((D2 @ qz) ** 2) / s**2 + 0.5 * np.sum((y - qz) ** 2)
        joint.append(j)
        with_occam.append(j + (T - 2) * float(OCCAM(np.log(s))))
    return np.array(joint), np.array(with_occam)


@pytest.mark.parametrize("seed", [0, 1])
def test_occam_term_recovers_how_freely_a_body_moves_where_the_joint_fit_collapses(seed):
    """The joint fit alone prefers the freest trajectory (it follows the noise: the
    light-object collapse); with the Occam term it is the marginal likelihood, whose
    minimum is at the true process sd."""
    grid = np.logspace(-3, 1, 81)  # steps of 12 %
    joint, with_occam = _random_walk_fits(seed, s_true=0.05, T=4000, grid=grid)
    assert np.argmin(joint) == len(grid) - 1  # collapses to the freest end of the grid
    # 4000 samples fix log s to a few percent; 25 % is two grid steps
    assert grid[np.argmin(with_occam)] == pytest.approx(0.05, rel=0.25)


# ------------------------------------------------------------------------------------
# the directions a contact holds (problem.occam_free_weights)

#: a box of half-extents (A, B) m resting on its bottom face, ground normal +y; levers of
#: its two bottom vertices, and the half length that puts the angle in length units
A, B = 0.04, 0.05
UP = np.array([0.0, 1.0])
BOTTOM = [(UP, np.array([-A, -B])), (UP, np.array([A, -B]))]
HALF = 0.05


def _free(rows, weights, half=HALF):
    from tacest.model.occam import occam_free_weights

    return np.asarray(ca.DM(occam_free_weights(rows, weights, half))).ravel()


def test_occam_free_weights_hold_what_the_contacts_hold():
    from tacest.model.occam import OCCAM_HELD_EPS as EPS

    # nothing touching: every direction free, exactly
    np.testing.assert_allclose(_free(BOTTOM, [0.0, 0.0]), [1.0, 1.0, 1.0], rtol=0, atol=1e-15)
    # resting on a face: height and angle held (each touching row takes a direction to
    # about EPS / (weight + EPS); two rows share two directions: below 2 EPS), x free
    x, y, ang = _free(BOTTOM, [1.0, 1.0])
    assert x == pytest.approx(1.0, abs=1e-12)
    assert y < 2 * EPS and ang < 2 * EPS
    # a finger pushing the side along x holds x too
    side = (np.array([1.0, 0.0]), np.array([-A, 0.02]))
    assert np.all(_free(BOTTOM + [side], [1.0, 1.0, 1.0]) < 2 * EPS)
    # on one vertex (tipping): one combination of height and angle held, one free
    x, y, ang = _free(BOTTOM, [0.0, 1.0])
    assert x == pytest.approx(1.0, abs=1e-12)
    assert 0.1 < y < 0.9 and 0.1 < ang < 0.9
    # a contact of weight 0.05 (a vertex 2 sig_gap above the ground) holds little
    assert np.all(_free(BOTTOM, [0.0025, 0.0025]) > 0.8)


def test_occam_free_weights_are_invariant_to_the_length_scale():
    """Levers and the half length in other units (mm for m): the same freedoms, to rounding."""
    scaled = [(n, 1000.0 * r) for n, r in BOTTOM + [(np.array([1.0, 0.0]), np.array([-A, 0.02]))]]
    np.testing.assert_allclose(_free(scaled, [1.0, 0.3, 0.5], 1000.0 * HALF),
                               _free(BOTTOM + [(np.array([1.0, 0.0]), np.array([-A, 0.02]))], [1.0, 0.3, 0.5]),
                               rtol=1e-12)

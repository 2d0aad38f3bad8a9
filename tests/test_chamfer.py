"""Chamfer metrics: closed-form answers, agreement with dense point sets, quadrature
accuracy against fine references, and invariance under rigid motions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import dblquad

from tacest.errors import TacestError
from tacest.geometry.chamfer import (
    chamfer_body,
    chamfer_placed,
    chamfer_placed_series,
    chamfer_points,
    chamfer_shapes,
    frame_indices,
)
from tacest.geometry.polygon import box_vertices, convex_hull_2d, polygon_perimeter, sample_polygon_boundary
from tacest.geometry.polytope import box_vertices_3d
from tacest.geometry.transforms import quat_from_axis_angle, quat_multiply, quat_to_matrix, rot2

#: Round-off: distances between points with 0.1 m coordinates carry ~1e-17 m error;
#: sums over thousands of samples stay below 1e-15 m.
ROUNDOFF = 1e-15
#: 2-D quadrature bound when the boundary distance is piecewise linear (shifted
#: polygons): the midpoint rule is exact on linear pieces and errs by at most h²/4 (h =
#: L/4000) in each of the <= 8 cells holding a kink, over the perimeter L:
#: 8 (L/4000)² / (4 L) = L / 8e6 <= 6e-8 m for L <= 0.48 m.
QUAD_2D = 6e-8
#: 3-D adaptive quadrature with the default 2000 cells: <= 1.8 µm measured against
#: 60 000-sample references (tacest/geometry/chamfer.py docstring); 5 µm leaves margin
#: and is 1/20 of the 0.1 mm the metric must resolve.
QUAD_3D = 5e-6
#: chamfer_body in 3-D: the alignment is refined on 1000 samples of each hull, and a
#: moved hull is triangulated (hence sampled) differently, so refinements of moved
#: copies end up to ~1 µm apart in value (measured: 0.01-1 µm on boxes and random
#: polytopes).  2 µm = 1/50 of the 0.1 mm target.
BODY_3D = 2e-6
#: chamfer_body in 2-D: the alignment is refined on 1000 samples, which sit elsewhere
#: on a moved polygon (its hull starts at another vertex): measured spread 0.05 µm on
#: random heptagons.  0.5 µm = 1/200 of the 0.1 mm target.
BODY_2D = 5e-7

SIDE = 0.1  # m


def random_rigid_2d(seed):
    rng = np.random.default_rng(seed)
    return rot2(rng.uniform(-np.pi, np.pi)), rng.normal(size=2) * 0.3


def random_rigid_3d(seed):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    return quat_to_matrix(q / np.linalg.norm(q)), rng.normal(size=3) * 0.3


# ---------------------------------------------------------------------------------
# point sets


def test_chamfer_points_table():
    A = np.array([[0.0, 0.0]])
    B = np.array([[1.0, 0.0], [3.0, 0.0]])
    # mean_a min_b = 1, mean_b min_a = (1 + 3) / 2 = 2  ->  1.5
    assert chamfer_points(A, B) == pytest.approx(1.5, abs=ROUNDOFF)
    assert chamfer_points(B, A) == pytest.approx(1.5, abs=ROUNDOFF)
    assert chamfer_points(B, B) == 0.0
    # weights: b-side mean becomes 0.75 * 1 + 0.25 * 3 = 1.5  ->  1.25
    assert chamfer_points(A, B, weights_b=[3.0, 1.0]) == pytest.approx(1.25, abs=ROUNDOFF)
    with pytest.raises(TacestError):
        chamfer_points(np.zeros((0, 2)), B)


def test_dense_point_sets_bracket_the_exact_value():
    """With the same samples, point-to-sample distances exceed the exact point-to-boundary
    ones by at most half the sample spacing h: exact <= points <= exact + h/2."""
    rng = np.random.default_rng(0)
    P = convex_hull_2d(rng.normal(size=(9, 2)) * 0.05)
    Q = convex_hull_2d(P @ rot2(0.05).T + [0.003, -0.002])
    n = 20000
    exact = chamfer_shapes(P, Q, n)
    pts = chamfer_points(sample_polygon_boundary(P, n), sample_polygon_boundary(Q, n))
    h = max(polygon_perimeter(P), polygon_perimeter(Q)) / n
    assert exact - ROUNDOFF <= pts <= exact + h / 2


# ---------------------------------------------------------------------------------
# closed forms


@pytest.mark.parametrize("d", [0.0005, 0.002, 0.02])
def test_square_shifted(d):
    """Square of side s and its copy shifted by d <= s/2 along x: from A's boundary,
    the left edge is d away, the right edge min(d, y, s - y) (integral s d - d²), top
    and bottom d²/2 each: total 2 s d over the perimeter 4 s -> d / 2; B alike."""
    S = box_vertices(SIDE, SIDE)
    assert chamfer_shapes(S, S + [d, 0.0]) == pytest.approx(d / 2, abs=QUAD_2D)


@pytest.mark.parametrize("w, h, d", [(0.1, 0.06, 0.002), (0.05, 0.12, 0.01)])
def test_rectangle_shifted(w, h, d):
    """w x h rectangle shifted by d (<= h/2, <= w) along x: the same integrals give
    2 h d over the perimeter 2 (w + h) -> h d / (w + h)."""
    R = box_vertices(w, h)
    assert chamfer_shapes(R, R + [d, 0.0]) == pytest.approx(h * d / (w + h), abs=QUAD_2D)


def cube_shift_chamfer(s, d):
    """Cube of side s and its copy shifted by d <= s/2 along x.  From A's surface: the
    face x = 0 is d away (area s²); on x = s the distance is min(d, distance to the
    face's edge), integral d (s - 2d)² + 2 s d² - 8 d³ / 3; the four side faces have
    distance d - x for x < d, 2 s d² in all.  Mean over 6 s²; B alike."""
    face = d * (s - 2 * d) ** 2 + 2 * s * d * d - 8 * d ** 3 / 3
    return (s * s * d + face + 2 * s * d * d) / (6 * s * s)


@pytest.mark.parametrize("d", [0.0001, 0.001, 0.01])
def test_cube_shifted(d):
    C = box_vertices_3d([SIDE] * 3)
    assert chamfer_shapes(C, C + [d, 0.0, 0.0]) == pytest.approx(cube_shift_chamfer(SIDE, d), abs=QUAD_3D)


def test_identical_shapes_are_zero():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(10, 2)) * 0.05
    V = rng.normal(size=(12, 3)) * 0.05
    assert chamfer_shapes(P, P) < ROUNDOFF  # every sample lies on the other boundary
    assert chamfer_shapes(V, V) < ROUNDOFF


# ---------------------------------------------------------------------------------
# quadrature against fine references


def test_quadrature_2d_against_fine_reference():
    """Random octagons 2 mm apart and turned by 3°: the default 4000 samples against
    400 000; worst-case bound for a 1-Lipschitz integrand: L / (4 n)."""
    rng = np.random.default_rng(2)
    P = rng.normal(size=(8, 2)) * 0.05
    Q = P @ rot2(np.deg2rad(3)).T + rng.normal(size=(8, 2)) * 0.002
    ref = chamfer_shapes(P, Q, 400_000)
    L = max(polygon_perimeter(convex_hull_2d(P)), polygon_perimeter(convex_hull_2d(Q)))
    assert abs(chamfer_shapes(P, Q) - ref) <= L / (4 * 4000)
    assert abs(chamfer_shapes(P, Q) - ref) <= 1e-8  # and in fact O(h²): measured 3e-10


@pytest.mark.parametrize("angle_deg, shift", [(1.0, 0.001), (10.0, 0.001), (10.0, 0.005)])
def test_quadrature_3d_against_fine_reference(angle_deg, shift):
    C = box_vertices_3d([SIDE] * 3)
    R = quat_to_matrix(quat_from_axis_angle([0.3, -0.5, 0.8], np.deg2rad(angle_deg)))
    other = C @ R.T + shift * np.array([0.6, 0.0, 0.8])
    ref = chamfer_shapes(C, other, 60_000)
    assert abs(chamfer_shapes(C, other) - ref) <= QUAD_3D


# ---------------------------------------------------------------------------------
# placed shapes over time


def test_frame_indices():
    np.testing.assert_array_equal(frame_indices(100), np.arange(100))
    np.testing.assert_array_equal(frame_indices(450), np.arange(0, 450, 3))
    assert len(frame_indices(200)) == 200 and len(frame_indices(201)) == 101


def test_chamfer_placed_known_answer_2d():
    w, h, d, T = 0.1, 0.06, 0.002, 50
    poses = np.zeros((T, 3))
    poses[:, 0] = np.linspace(0.0, 0.05, T)
    est = poses + [d, 0.0, 0.0]
    frames, vals = chamfer_placed_series(box_vertices(w, h), est, box_vertices(w, h), poses)
    np.testing.assert_array_equal(frames, np.arange(T))
    np.testing.assert_allclose(vals, h * d / (w + h), atol=QUAD_2D)


def test_chamfer_placed_invariant_under_common_motion():
    """The same rigid motion of the world applied to both trajectories changes nothing."""
    rng = np.random.default_rng(3)
    T = 30
    # 2-D
    pose_t = np.column_stack([np.linspace(0, 0.1, T), np.full(T, 0.03), np.linspace(0, 1, T)])
    pose_e = pose_t + rng.normal(size=(T, 3)) * [0.002, 0.002, 0.02]
    Ve, Vt = box_vertices(0.1, 0.06) * 1.05, box_vertices(0.1, 0.06)
    base = chamfer_placed(Ve, pose_e, Vt, pose_t)
    G, g = random_rigid_2d(4)
    phi = math.atan2(G[1, 0], G[0, 0])

    def move(p):
        out = p.copy()
        out[:, :2] = p[:, :2] @ G.T + g
        out[:, 2] += phi
        return out

    assert chamfer_placed(Ve, move(pose_e), Vt, move(pose_t)) == pytest.approx(base, abs=1e-12)
    # 3-D
    q_t = quat_from_axis_angle([0.0, 0.0, 1.0], np.linspace(0, 1, T))
    pose_t3 = np.column_stack([np.linspace(0, 0.1, T), np.zeros(T), np.full(T, 0.03), q_t])
    pose_e3 = pose_t3.copy()
    pose_e3[:, :3] += rng.normal(size=(T, 3)) * 0.002
    pose_e3[:, 3:] = quat_multiply(quat_from_axis_angle([1.0, 0.0, 0.0], 0.02), q_t)
    Ve3, Vt3 = box_vertices_3d([0.1, 0.08, 0.06]) * 1.05, box_vertices_3d([0.1, 0.08, 0.06])
    base3 = chamfer_placed(Ve3, pose_e3, Vt3, pose_t3)
    qg = np.array([0.8, 0.1, -0.3, 0.5])
    qg /= np.linalg.norm(qg)
    Gm, g3 = quat_to_matrix(qg), np.array([0.3, -0.2, 0.1])

    def move3(p):
        out = p.copy()
        out[:, :3] = p[:, :3] @ Gm.T + g3
        out[:, 3:] = quat_multiply(qg, p[:, 3:])
        return out

    assert chamfer_placed(Ve3, move3(pose_e3), Vt3, move3(pose_t3)) == pytest.approx(base3, abs=1e-12)


def test_chamfer_placed_errors():
    V = box_vertices(0.1, 0.1)
    with pytest.raises(TacestError, match="length"):
        chamfer_placed(V, np.zeros((5, 3)), V, np.zeros((6, 3)))
    with pytest.raises(TacestError, match="shape"):
        chamfer_placed(V, np.zeros((5, 7)), V, np.zeros((5, 7)))
    bad = np.zeros((5, 3))
    bad[2, 0] = np.nan
    with pytest.raises(TacestError, match="NaN"):
        chamfer_placed(V, bad, V, np.zeros((5, 3)))
    with pytest.raises(TacestError, match="2-D shape with a 3-D"):
        chamfer_shapes(V, box_vertices_3d([0.1] * 3))


# ---------------------------------------------------------------------------------
# best rigid alignment


def concentric_squares(a, e):
    """Square of side a centred in one of side b = a + 2e.  From the small one every
    point is e away; from the large one e over a length a per side, and
    sqrt(e² + u²) for u in [0, e] next to each corner:
    (a e + 2 ∫0^e sqrt(e² + u²) du) / b per side, ∫ = e² (√2 + asinh 1) / 2."""
    b = a + 2 * e
    return 0.5 * (e + (a * e + e * e * (math.sqrt(2) + math.asinh(1.0))) / b)


def concentric_cubes(a, e):
    """Cube of side a centred in one of side b = a + 2e (3-D analogue): on each face
    of the large cube the distance is sqrt(e² + u² + v²), u, v the overhangs beyond
    the small face; integrated numerically to 1e-12."""
    b = a + 2 * e
    edge = 2 * a * (e * e * (math.sqrt(2) + math.asinh(1.0)) / 2)  # 4 strips of a x e
    corner = dblquad(lambda v, u: math.sqrt(e * e + u * u + v * v), 0, e, 0, e, epsabs=1e-16)[0]
    face = a * a * e + 2 * edge + 4 * corner
    return 0.5 * (e + face / (b * b))


def test_chamfer_body_2d_known_and_invariant():
    small, big = box_vertices(SIDE, SIDE), box_vertices(SIDE + 0.02, SIDE + 0.02)
    expect = concentric_squares(SIDE, 0.01)
    for seed in range(2):
        R, t = random_rigid_2d(seed)
        assert chamfer_body(small, big @ R.T + t) == pytest.approx(expect, abs=BODY_2D)
        assert chamfer_body(small @ R.T + t, big) == pytest.approx(expect, abs=BODY_2D)
    # a generic pair: the value does not depend on where either shape sits
    rng = np.random.default_rng(5)
    P = rng.normal(size=(7, 2)) * 0.05
    Q = P * [1.1, 0.95] + rng.normal(size=(7, 2)) * 0.003
    base, Rb, tb = chamfer_body(P, Q, return_transform=True)
    assert base == pytest.approx(chamfer_shapes(P @ Rb.T + tb, Q), abs=ROUNDOFF * 1e3)
    for seed in range(2):
        R, t = random_rigid_2d(10 + seed)
        assert chamfer_body(P, Q @ R.T + t) == pytest.approx(base, abs=BODY_2D)
    # a moved copy aligns back to (nearly) zero: ICP stops at 1e-10 size steps
    R, t = random_rigid_2d(20)
    assert chamfer_body(P, P @ R.T + t) < 1e-9


def test_chamfer_body_3d_known_and_invariant():
    small, big = box_vertices_3d([SIDE] * 3), box_vertices_3d([SIDE + 0.02] * 3)
    expect = concentric_cubes(SIDE, 0.01)
    for seed in range(2):
        R, t = random_rigid_3d(seed)
        assert chamfer_body(small, big @ R.T + t) == pytest.approx(expect, abs=BODY_3D + QUAD_3D)
    # a box against a slightly different box, either one moved
    A, B = box_vertices_3d([0.1, 0.1, 0.1]), box_vertices_3d([0.1, 0.11, 0.12])
    base = chamfer_body(A, B)
    R, t = random_rigid_3d(7)
    assert chamfer_body(A, B @ R.T + t) == pytest.approx(base, abs=BODY_3D)
    assert chamfer_body(A @ R.T + t, B) == pytest.approx(base, abs=BODY_3D)
    # a moved copy of a generic polytope aligns back to ~0 (1e-7 m: ICP steps stop at
    # 1e-10 size, far below; 1e-7 leaves room for the samples of a re-triangulated hull)
    rng = np.random.default_rng(8)
    V = rng.normal(size=(10, 3)) * 0.05
    assert chamfer_body(V, V @ R.T + t) < 1e-7

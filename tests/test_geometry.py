"""Numpy geometry: hand-computed tables for polygons, boxes and polytopes, quaternion
identities, boundary/surface sampling, and the fast exact boundary distance against
brute-force references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.geometry import polygon as pg
from tacest.geometry import polytope as pt
from tacest.geometry import transforms as tf
from tacest.geometry.chamfer import Shape

#: Float64 round-off for quantities of order 1 computed in a few dozen operations.
EXACT = 1e-12


# ---------------------------------------------------------------------------------
# polygons


UNIT_SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
RIGHT_TRIANGLE = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


@pytest.mark.parametrize("verts, area, centroid, J", [
    # square: J = (1/12 + 1/12) about the centre
    (UNIT_SQUARE, 1.0, [0.5, 0.5], 1.0 / 6.0),
    # legs 1, 1: I_x = I_y = b h³ / 36 about the centroid, J = 1/18
    (RIGHT_TRIANGLE, 0.5, [1.0 / 3.0, 1.0 / 3.0], 1.0 / 18.0),
    # 2 x 1 rectangle at (3, -1): J = A (w² + h²) / 12 = 2 * 5 / 12
    (np.array([[2.0, -1.5], [4.0, -1.5], [4.0, -0.5], [2.0, -0.5]]), 2.0, [3.0, -1.0], 10.0 / 12.0),
])
def test_polygon_table(verts, area, centroid, J):
    assert pg.polygon_area(verts) == pytest.approx(area, abs=EXACT)
    np.testing.assert_allclose(pg.polygon_centroid(verts), centroid, atol=EXACT)
    assert pg.polygon_second_moment(verts) == pytest.approx(J, abs=EXACT)
    # orientation does not matter for area, centroid and J
    assert pg.polygon_area(verts[::-1]) == pytest.approx(area, abs=EXACT)
    assert pg.polygon_second_moment(verts[::-1]) == pytest.approx(J, abs=EXACT)
    assert pg.signed_area(verts) > 0 and pg.signed_area(verts[::-1]) < 0


@pytest.mark.parametrize("w, h, m", [(0.1, 0.06, 0.5), (1.0, 1.0, 1.0), (0.02, 0.3, 2.0)])
def test_box_inertia(w, h, m):
    V = pg.box_vertices(w, h)
    assert pg.polygon_area(V) == pytest.approx(w * h, rel=EXACT)
    np.testing.assert_allclose(pg.polygon_centroid(V), [0.0, 0.0], atol=EXACT)
    assert pg.polygon_inertia(V, m) == pytest.approx(m * (w * w + h * h) / 12.0, rel=EXACT)
    assert pg.signed_area(V) > 0  # CCW
    with pytest.raises(TacestError):
        pg.box_vertices(0.0, 1.0)


def test_convex_hull_2d():
    rng = np.random.default_rng(1)
    inner = rng.uniform(-0.4, 0.4, size=(50, 2))
    # the corners, edge midpoints (collinear: dropped) and interior points, shuffled
    pts = np.vstack([UNIT_SQUARE - 0.5, [[0.0, -0.5], [0.5, 0.0]], inner, UNIT_SQUARE - 0.5])
    pts = pts[rng.permutation(len(pts))]
    H = pg.convex_hull_2d(pts)
    assert H.shape == (4, 2)
    assert pg.signed_area(H) == pytest.approx(1.0, abs=EXACT)  # CCW, area 1
    assert {tuple(p) for p in H} == {tuple(p) for p in UNIT_SQUARE - 0.5}
    np.testing.assert_array_equal(H[0], [-0.5, -0.5])  # starts at lowest x, then y
    for bad in ([[0, 0], [1, 1]], [[0, 0], [1, 1], [2, 2], [3, 3]], [[0, 0], [1, 0], [np.nan, 1]]):
        with pytest.raises(TacestError):
            pg.convex_hull_2d(np.array(bad, float))


def test_sample_polygon_boundary():
    V = pg.box_vertices(0.1, 0.06)
    n = 320  # perimeter 0.32 m -> spacing exactly 1 mm
    P = pg.sample_polygon_boundary(V, n)
    assert P.shape == (n, 2)
    # every point on the boundary (round-off of 0.1 m coordinates)
    assert np.max(pg.polygon_boundary_distance(P, V)) < EXACT
    # uniform by arc length: consecutive chords are 1 mm except across a corner,
    # where the chord is shorter than the 1 mm arc
    gaps = np.linalg.norm(np.diff(np.vstack([P, P[:1]]), axis=0), axis=1)
    assert np.max(gaps) == pytest.approx(1e-3, abs=EXACT)
    assert np.sum(np.abs(gaps - 1e-3) > EXACT) <= 4
    # the first point sits half a spacing from vertex 0
    np.testing.assert_allclose(P[0], V[0] + [0.5e-3, 0.0], atol=EXACT)


# ---------------------------------------------------------------------------------
# transforms


def test_rot2_and_wrap():
    R = tf.rot2(np.pi / 2)
    np.testing.assert_allclose(R @ [1.0, 0.0], [0.0, 1.0], atol=EXACT)
    assert tf.rot2(np.zeros(5)).shape == (5, 2, 2)
    assert tf.angle_of_rot2(tf.rot2(0.3)) == pytest.approx(0.3, abs=EXACT)
    np.testing.assert_allclose(tf.wrap_angle([np.pi + 0.1, -np.pi - 0.1, 0.2, 7.0]),
                               [-np.pi + 0.1, np.pi - 0.1, 0.2, 7.0 - 2 * np.pi], atol=EXACT)


def test_quaternions():
    rng = np.random.default_rng(2)
    a = tf.quat_normalize(rng.normal(size=(10, 4)))
    b = tf.quat_normalize(rng.normal(size=(10, 4)))
    Ra, Rb = tf.quat_to_matrix(a), tf.quat_to_matrix(b)
    # products compose like matrices; conjugate is the inverse; rotation matrices are SO(3)
    np.testing.assert_allclose(tf.quat_to_matrix(tf.quat_multiply(a, b)), Ra @ Rb, atol=EXACT)
    np.testing.assert_allclose(tf.quat_to_matrix(tf.quat_conjugate(a)), np.swapaxes(Ra, -1, -2), atol=EXACT)
    np.testing.assert_allclose(Ra @ np.swapaxes(Ra, -1, -2), np.broadcast_to(np.eye(3), Ra.shape), atol=EXACT)
    np.testing.assert_allclose(np.linalg.det(Ra), 1.0, atol=EXACT)
    # matrix round trip (up to the sign of q)
    back = tf.quat_from_matrix(Ra)
    np.testing.assert_allclose(np.abs(np.sum(back * a, axis=1)), 1.0, atol=EXACT)
    v = rng.normal(size=(10, 3))
    np.testing.assert_allclose(tf.quat_rotate(a, v), np.einsum("nij,nj->ni", Ra, v), atol=EXACT)
    # a 90° turn about z
    qz = tf.quat_from_axis_angle([0.0, 0.0, 1.0], np.pi / 2)
    np.testing.assert_allclose(tf.quat_rotate(qz, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=EXACT)
    # geodesic angle: known, sign-blind, symmetric; accurate near zero
    q1 = tf.quat_from_axis_angle([1.0, 1.0, 0.0], 0.3)
    assert tf.quat_angle(q1, [1.0, 0.0, 0.0, 0.0]) == pytest.approx(0.3, abs=EXACT)
    assert tf.quat_angle(q1, -q1) == pytest.approx(0.0, abs=EXACT)
    assert tf.quat_angle(a, b) == pytest.approx(tf.quat_angle(b, a), abs=EXACT)
    tiny = tf.quat_from_axis_angle([0.0, 1.0, 0.0], 1e-9)
    assert tf.quat_angle(tiny, [1.0, 0.0, 0.0, 0.0]) == pytest.approx(1e-9, rel=1e-6)
    with pytest.raises(TacestError):
        tf.quat_normalize([0.0, 0.0, 0.0, 0.0])


def test_poses_and_cube_rotations():
    pose2 = np.array([1.0, 2.0, np.pi / 2])
    np.testing.assert_allclose(tf.transform_points(pose2, [[1.0, 0.0]], 2), [[1.0, 3.0]], atol=EXACT)
    pose3 = np.concatenate([[1.0, 2.0, 3.0], tf.quat_from_axis_angle([0.0, 0.0, 1.0], np.pi / 2)])
    np.testing.assert_allclose(tf.transform_points(pose3, [[1.0, 0.0, 0.0]], 3), [[1.0, 3.0, 3.0]], atol=EXACT)
    # relative transform: body-from coordinates -> body-to coordinates
    rng = np.random.default_rng(3)
    pa = np.concatenate([rng.normal(size=3), tf.quat_normalize(rng.normal(size=4))])
    pb = np.concatenate([rng.normal(size=3), tf.quat_normalize(rng.normal(size=4))])
    R, t = tf.relative_transform(pa, pb, 3)
    x = rng.normal(size=(5, 3))
    world = tf.transform_points(pa, x, 3)
    np.testing.assert_allclose(tf.transform_points(pb, x @ R.T + t, 3), world, atol=EXACT)
    C = tf.cube_rotations()
    assert C.shape == (24, 3, 3)
    np.testing.assert_array_equal(C[0], np.eye(3))
    assert len({tuple(M.ravel()) for M in C}) == 24
    np.testing.assert_allclose(np.linalg.det(C), 1.0)


# ---------------------------------------------------------------------------------
# polytopes


def test_box_polytope_table():
    w, h, d, m = 0.1, 0.2, 0.3, 1.2
    V = pt.box_vertices_3d([w, h, d]) + [1.0, -2.0, 0.5]
    assert pt.polytope_volume(V) == pytest.approx(w * h * d, rel=1e-12)
    np.testing.assert_allclose(pt.polytope_centroid(V), [1.0, -2.0, 0.5], atol=EXACT)
    I = pt.polytope_inertia(V, m)
    np.testing.assert_allclose(I, np.diag([h * h + d * d, w * w + d * d, w * w + h * h]) * m / 12.0, atol=1e-12)
    with pytest.raises(TacestError):
        pt.convex_hull_mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float))  # flat
    with pytest.raises(TacestError):
        pt.box_vertices_3d([1.0, -1.0, 1.0])


def test_sample_polytope_surface():
    V = pt.box_vertices_3d([1.0, 2.0, 3.0])
    P, w = pt.sample_polytope_surface(V, 5000, return_weights=True)
    assert abs(len(P) - 5000) < 500  # "about n": rounding of per-triangle counts
    assert w.sum() == pytest.approx(1.0, abs=EXACT)
    surf = pt.PolytopeSurface(V)
    assert np.max(surf.distance(P)) < 1e-12  # on the surface
    # uniform by area: the weight on each pair of faces is its share of the area (22)
    for axis, share in ((0, 2 * 6 / 22), (1, 2 * 3 / 22), (2, 2 * 2 / 22)):
        on = np.isclose(np.abs(P[:, axis]), [0.5, 1.0, 1.5][axis])
        assert w[on].sum() == pytest.approx(share, abs=EXACT)
    # the quadrature integrates linear functions exactly: mean of z² over the surface
    # of a cube of side 2 is (2 faces * 1 + 4 faces * 1/3) / 6 = 5/9 (z² is quadratic,
    # so allow the O(h²) error of the centroid rule: h ~ 2/22 -> 1e-2 * 2 / 12)
    Pc, wc = pt.sample_polytope_surface(pt.box_vertices_3d([2.0, 2.0, 2.0]), 3000, return_weights=True)
    assert wc @ Pc[:, 2] == pytest.approx(0.0, abs=EXACT)
    assert wc @ Pc[:, 2] ** 2 == pytest.approx(5.0 / 9.0, abs=2e-3)
    # random variant: exactly n points, reproducible by seed
    R1 = pt.sample_polytope_surface(V, 100, seed=7)
    R2 = pt.sample_polytope_surface(V, 100, seed=7)
    assert R1.shape == (100, 3)
    np.testing.assert_array_equal(R1, R2)


# ---------------------------------------------------------------------------------
# the fast exact boundary distance used by the Chamfer metrics


def test_convex_boundary_matches_brute_force_2d():
    rng = np.random.default_rng(4)
    V = pg.convex_hull_2d(rng.normal(size=(12, 2)) * 0.05)
    P = rng.normal(size=(3000, 2)) * 0.06
    K = len(V)
    P[:K] = V  # exactly on the corners
    P[K:2 * K] = 0.5 * (V + np.roll(V, -1, axis=0))  # exactly on the edges
    d_fast, c, signed, n = Shape(V).closest(P)
    d_ref = pg.polygon_boundary_distance(P, V)
    np.testing.assert_allclose(Shape(V).distance(P), d_ref, atol=EXACT)
    np.testing.assert_allclose(d_fast, d_ref, atol=EXACT)
    np.testing.assert_allclose(np.linalg.norm(P - c, axis=1), d_fast, atol=EXACT)
    np.testing.assert_allclose(np.sum(n * (P - c), axis=1), signed, atol=EXACT)
    assert np.max(pg.polygon_boundary_distance(c, V)) < EXACT  # closest points on the boundary


def test_convex_boundary_matches_brute_force_3d():
    rng = np.random.default_rng(5)
    for V in (rng.normal(size=(14, 3)) * 0.05, pt.box_vertices_3d([0.1, 0.06, 0.08])):
        P = rng.normal(size=(3000, 3)) * 0.07
        d_fast, c, signed, n = Shape(V).closest(P)
        np.testing.assert_allclose(Shape(V).distance(P), d_fast, atol=EXACT)
        surf = pt.PolytopeSurface(V)
        d_ref, c_ref = surf.closest(P)
        np.testing.assert_allclose(d_fast, d_ref, atol=EXACT)
        np.testing.assert_allclose(np.linalg.norm(P - c, axis=1), d_fast, atol=EXACT)
        np.testing.assert_allclose(np.sum(n * (P - c), axis=1), signed, atol=EXACT)
        assert np.max(surf.distance(c)) < EXACT
        inside = signed < 0
        assert 0 < inside.sum() < len(P)  # both branches exercised


def test_shape_size_and_centroid():
    s = Shape(pt.box_vertices_3d([0.1, 0.2, 0.3]) + 1.0)
    assert s.size == pytest.approx(0.3, abs=EXACT)
    np.testing.assert_allclose(s.centroid, [1.0, 1.0, 1.0], atol=EXACT)
    assert s.boundary.n.shape == (6, 3)  # coplanar triangles merged into 6 planes
    assert s.boundary.seg_a.shape == (12, 3)  # 12 box edges, face diagonals dropped
    with pytest.raises(TacestError):
        Shape(np.zeros((3, 4)))
    assert math.isfinite(Shape(RIGHT_TRIANGLE).size)


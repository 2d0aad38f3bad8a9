"""The polygon sampler of polygon:K estimates (tacest.estimation.smc2d with
SMCSettings.polygon_vertices): its random convex hypotheses, their mass properties
(tacest.model.forward2d.polygon_hypotheses) and the start it gives the NLP."""

from __future__ import annotations

import numpy as np
import pytest

from tacest.geometry.polygon import polygon_centroid, polygon_inertia


def _cross_z(P):
    """(n, K) z of the cross product of consecutive edges of polygons P (n, K, 2)."""
    E = np.roll(P, -1, axis=1) - P
    E1 = np.roll(E, -1, axis=1)
    return E[..., 0] * E1[..., 1] - E[..., 1] * E1[..., 0]


@pytest.mark.parametrize("K", [3, 5, 8])
def test_random_unit_polygons_are_convex_span_the_unit_square_and_rest_on_a_stable_face(K):
    """Every hypothesis: K vertices, CCW and convex (no right turn beyond rounding:
    padded midpoints are straight, 1e-12), spanning [-1, 1] in x and y, its first face
    flat at the bottom (y = -1), and the centroid above that face (a face it can rest on:
    the face nearest the centroid always is)."""
    from tacest.estimation.smc2d import RECTANGLE_FRACTION, random_unit_polygons

    P = random_unit_polygons(np.random.default_rng(3), 200, K)
    assert P.shape == (200, K, 2)
    assert np.all(_cross_z(P) >= -1e-12)
    np.testing.assert_allclose(P.min(axis=1), -1.0, atol=1e-12)
    np.testing.assert_allclose(P.max(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(P[:, 0, 1], -1.0, atol=1e-12)
    np.testing.assert_allclose(P[:, 1, 1], -1.0, atol=1e-12)
    for poly in P:  # the bottom face: every vertex at y = -1 (a padded face has several)
        bottom = poly[np.abs(poly[:, 1] + 1.0) < 1e-12, 0]
        assert bottom.min() - 1e-9 <= polygon_centroid(poly)[0] <= bottom.max() + 1e-9
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    rect = [all(np.min(np.linalg.norm(p - c, axis=1)) < 1e-12 for c in corners) for p in P]
    assert sum(rect) >= (round(RECTANGLE_FRACTION * 200) if K >= 4 else 0)
    # reproducible from the generator's seed
    np.testing.assert_array_equal(P, random_unit_polygons(np.random.default_rng(3), 200, K))


def test_polygon_hypotheses_have_the_lamina_mass_properties_wherever_the_vertices_are_given():
    """Known answers: a rectangle's hypothesis is the box's (vertices, m (w² + h²)/12);
    any polygon's inertia is the lamina's about its centroid (tacest.geometry.polygon,
    an independent implementation), its vertices re-centred there, whatever frame they
    came in (a translation changes nothing)."""
    from tacest.model.forward2d import box_hypotheses, polygon_hypotheses

    w, h, m = np.array([0.08, 0.12]), np.array([0.05, 0.2]), np.array([0.3, 1.1])
    box = box_hypotheses(w, h, m, [0.4, 0.5], [0.6, 0.7])
    poly = polygon_hypotheses(box.vertices + np.array([0.3, -0.2]), m, [0.4, 0.5], [0.6, 0.7])
    np.testing.assert_allclose(poly.vertices, box.vertices, atol=1e-15)
    np.testing.assert_allclose(poly.inertia, m * (w ** 2 + h ** 2) / 12, rtol=1e-12)
    from tacest.estimation.smc2d import random_unit_polygons

    V = 0.04 * random_unit_polygons(np.random.default_rng(0), 30, 7) + np.array([0.5, 0.1])
    hyp = polygon_hypotheses(V, np.full(30, 0.7), np.zeros(30), np.zeros(30))
    for v, vc, inertia in zip(V, hyp.vertices, hyp.inertia):
        np.testing.assert_allclose(vc, v - polygon_centroid(v), atol=1e-15)
        assert inertia == pytest.approx(polygon_inertia(v, 0.7), rel=1e-9)


def test_a_box_sampler_draws_what_it_always_drew():
    """polygon_vertices 0 (box estimates): the unit polygons are not drawn, so the
    box sampler's random stream, and with it every box estimate, is unchanged."""
    from tacest.estimation.smc2d import _Particles

    a = _Particles(64, np.random.default_rng(1), 0.1, 0.5, True, np.array([0.1, 0.08]))
    b = _Particles(64, np.random.default_rng(1), 0.1, 0.5, True, np.array([0.1, 0.08]), polygon_vertices=8)
    assert a.unit is None and b.unit.shape == (64, 8, 2)
    for key in ("extents", "mass", "mu_g", "mu_f"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    np.testing.assert_array_equal(a.hypotheses().vertices, _Particles(
        64, np.random.default_rng(1), 0.1, 0.5, True, np.array([0.1, 0.08])).hypotheses().vertices)

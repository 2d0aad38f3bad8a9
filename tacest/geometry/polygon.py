"""Convex polygons in numpy: hull, area, centroid, second moment, boundary samples
and exact point-to-boundary distances.

A polygon is ``vertices : (K, 2) float, m``, ordered counter-clockwise (CCW), without
repeating the first vertex.  Functions that need a convex CCW polygon say so; use
:func:`convex_hull_2d` to get one from any point cloud.
"""

from __future__ import annotations

import numpy as np

from tacest.errors import TacestError

#: Relative tolerance (to the extent of the point cloud) under which three points
#: count as collinear in the hull, and under which a hull counts as degenerate.
#: 1e-12 is ~1e4 float64 ulps: it drops exactly-collinear points (box edges written
#: with a midpoint) without merging distinct vertices of any real object.
HULL_REL_TOL = 1e-12


def _cross(o, a, b):
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def convex_hull_2d(points) -> np.ndarray:
    """Convex hull of 2-D points, CCW, collinear points dropped.

    points : (N, 2) float, m (any order, duplicates allowed).
    Returns (K, 2) float, K >= 3, starting at the lowest-x (then lowest-y) vertex.
    Raises TacestError when the points span no area (fewer than 3, collinear, NaN).
    Andrew's monotone chain, O(N log N), deterministic.
    """
    P = np.asarray(points, float)
    if P.ndim != 2 or P.shape[1] != 2:
        raise TacestError(f"polygon vertices must have shape (K, 2), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise TacestError("polygon vertices contain NaN or inf")
    P = np.unique(P, axis=0)  # sorted by x, then y
    if P.shape[0] < 3:
        raise TacestError(f"a polygon needs at least 3 distinct vertices, got {P.shape[0]}")
    scale = float(np.max(np.ptp(P, axis=0)))
    eps = HULL_REL_TOL * scale * scale

    def half(points):
        chain = []
        for p in points:
            while len(chain) >= 2 and _cross(chain[-2], chain[-1], p) <= eps:
                chain.pop()
            chain.append(p)
        return chain

    lower = half(P)
    upper = half(P[::-1])
    hull = np.array(lower[:-1] + upper[:-1])
    if hull.shape[0] < 3 or polygon_area(hull) <= eps:
        raise TacestError("polygon vertices are collinear: the shape has no area")
    return hull


def signed_area(vertices) -> float:
    """Signed area (m²) of a simple polygon (K, 2): positive when CCW (shoelace)."""
    V = np.asarray(vertices, float)
    x, y = V[:, 0], V[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def polygon_area(vertices) -> float:
    """Area (m²) of a simple polygon (K, 2), either orientation."""
    return abs(signed_area(vertices))


def polygon_centroid(vertices) -> np.ndarray:
    """Area centroid (2,) m of a simple polygon (K, 2) with non-zero area."""
    V = np.asarray(vertices, float)
    x, y = V[:, 0], V[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cr = x * y1 - x1 * y
    A = 0.5 * np.sum(cr)
    if A == 0:
        raise TacestError("polygon has zero area: no centroid")
    return np.array([np.sum((x + x1) * cr), np.sum((y + y1) * cr)]) / (6.0 * A)


def polygon_second_moment(vertices) -> float:
    """Polar second moment of area about the centroid, ``J = ∫ |p - c|² dA`` (m⁴).

    vertices : (K, 2) simple polygon.  A uniform lamina of mass m has moment of
    inertia ``m * J / area`` about its centroid (see :func:`polygon_inertia`).
    Unit square: J = 1/6.
    """
    V = np.asarray(vertices, float)
    c = polygon_centroid(V)
    V = V - c  # about the centroid: better conditioned than the parallel-axis shift
    x, y = V[:, 0], V[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cr = x * y1 - x1 * y
    J = np.sum(cr * (x * x + x * x1 + x1 * x1 + y * y + y * y1 + y1 * y1)) / 12.0
    return abs(float(J))


def polygon_inertia(vertices, mass: float) -> float:
    """Moment of inertia (kg·m²) about the centroid of a uniform lamina of ``mass`` kg."""
    return float(mass) * polygon_second_moment(vertices) / polygon_area(vertices)


def polygon_perimeter(vertices) -> float:
    """Perimeter (m) of a closed polygon (K, 2)."""
    V = np.asarray(vertices, float)
    return float(np.sum(np.linalg.norm(np.roll(V, -1, axis=0) - V, axis=1)))


def box_vertices(w: float, h: float) -> np.ndarray:
    """Rectangle of width ``w`` (along x) and height ``h`` (along y), m, centred at the
    origin, CCW from the bottom-left corner: (4, 2)."""
    if not (w > 0 and h > 0):
        raise TacestError(f"box sides must be > 0, got {w} x {h}")
    a, b = 0.5 * float(w), 0.5 * float(h)
    return np.array([[-a, -b], [a, -b], [a, b], [-a, b]])


def sample_polygon_boundary(vertices, n: int) -> np.ndarray:
    """``n`` points spaced uniformly by arc length along a closed polygon's boundary.

    vertices : (K, 2), m, in boundary order.  Returns (n, 2), m.
    Point i sits at arc length ``(i + 1/2) * L / n`` from vertex 0 (the midpoints of
    n equal arcs), so the points are a midpoint quadrature rule for boundary means:
    for a 1-Lipschitz function the error of the mean is at most ``L / (4 n)``.
    """
    V = np.asarray(vertices, float)
    n = int(n)
    if n < 1:
        raise TacestError(f"number of samples must be >= 1, got {n}")
    E = np.roll(V, -1, axis=0) - V
    seg = np.linalg.norm(E, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    L = cum[-1]
    if L <= 0:
        raise TacestError("polygon has zero perimeter")
    s = (np.arange(n) + 0.5) * (L / n)
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    u = (s - cum[k]) / np.where(seg[k] > 0, seg[k], 1.0)
    return V[k] + u[:, None] * E[k]


def point_segment_distance(points, a, b) -> np.ndarray:
    """Distances (N, M) from points (N, D) to segments ``[a_j, b_j]`` (M, D)."""
    P = np.asarray(points, float)[:, None, :]
    a = np.asarray(a, float)[None]
    d = np.asarray(b, float)[None] - a
    dd = np.sum(d * d, axis=-1)
    u = np.clip(np.sum((P - a) * d, axis=-1) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    return np.linalg.norm(P - (a + u[..., None] * d), axis=-1)


def polygon_boundary_distance(points, vertices) -> np.ndarray:
    """Exact distance (N,) m from points (N, 2) to the boundary of a closed polygon
    (K, 2): the minimum over its K edges (zero on the boundary, positive inside too).

    Cost O(N K) memory and time; call in chunks for huge N.
    """
    V = np.asarray(vertices, float)
    P = np.asarray(points, float).reshape(-1, 2)
    out = np.empty(P.shape[0])
    chunk = max(1, 2_000_000 // max(1, V.shape[0]))
    for i in range(0, P.shape[0], chunk):
        out[i:i + chunk] = point_segment_distance(P[i:i + chunk], V, np.roll(V, -1, axis=0)).min(axis=1)
    return out


def convex_signed_distance(points, vertices) -> np.ndarray:
    """Signed distance (...,) m of points (..., 2) to convex CCW polygons (..., K, 2),
    broadcast over the leading axes (e.g. N points against N polygons): > 0 outside (the
    distance to the nearest edge segment), < 0 inside (the largest edge-line distance).
    The numeric twin of :func:`tacest.geometry.shapes.signed_distance_polygon`."""
    P = np.asarray(points, float)[..., None, :]  # (..., 1, 2)
    A = np.asarray(vertices, float)
    E = np.roll(A, -1, axis=-2) - A  # (..., K, 2) edges
    le = np.linalg.norm(E, axis=-1)
    nrm = np.stack([E[..., 1], -E[..., 0]], -1) / np.where(le > 0, le, 1.0)[..., None]  # outward (CCW)
    W = P - A
    d_face = np.sum(W * nrm, axis=-1)
    u = np.clip(np.sum(W * E, axis=-1) / np.where(le > 0, le * le, 1.0), 0.0, 1.0)
    d_seg = np.linalg.norm(W - u[..., None] * E, axis=-1)
    inside = np.all(d_face <= 0, axis=-1)
    return np.where(inside, d_face.max(axis=-1), d_seg.min(axis=-1))

"""Convex polytopes (3-D) in numpy + trimesh: hull mesh, volume, centroid, inertia,
surface samples and exact point-to-surface distances.

A polytope is given by ``vertices : (K, 3) float, m`` (any order; interior points are
ignored): the shape is their convex hull.  trimesh is imported lazily.
"""

from __future__ import annotations

import numpy as np

from tacest.errors import TacestError

#: A hull whose volume is below this fraction of (extent)³ is flat: no solid shape.
#: 1e-9 is far below any real object (a 10 cm cube of 0.1 mm thickness is 1e-3)
#: yet far above float64 round-off of the hull volume (~1e-15 relative).
FLAT_REL_TOL = 1e-9


def convex_hull_mesh(vertices):
    """Convex hull of 3-D points as a watertight, outward-oriented ``trimesh.Trimesh``.

    vertices : (K, 3) float, m.  Raises TacestError when they span no volume.
    """
    import trimesh

    V = np.asarray(vertices, float)
    if V.ndim != 2 or V.shape[1] != 3:
        raise TacestError(f"polytope vertices must have shape (K, 3), got {V.shape}")
    if not np.all(np.isfinite(V)):
        raise TacestError("polytope vertices contain NaN or inf")
    if np.unique(V, axis=0).shape[0] < 4:
        raise TacestError("a polytope needs at least 4 distinct vertices")
    scale = float(np.max(np.ptp(V, axis=0)))
    try:
        mesh = trimesh.convex.convex_hull(V)
    except Exception as exc:  # scipy QhullError for flat or degenerate input
        raise TacestError(f"polytope vertices span no volume ({exc.__class__.__name__})") from None
    if not (mesh.volume > FLAT_REL_TOL * scale ** 3):
        raise TacestError("polytope vertices are (nearly) coplanar: the shape has no volume")
    return mesh


def polytope_volume(vertices) -> float:
    """Volume (m³) of the convex hull of ``vertices`` (K, 3)."""
    return float(convex_hull_mesh(vertices).volume)


def polytope_centroid(vertices) -> np.ndarray:
    """Volume centroid (3,) m of the convex hull of ``vertices`` (K, 3)."""
    return np.asarray(convex_hull_mesh(vertices).center_mass, float)


def polytope_inertia(vertices, mass: float) -> np.ndarray:
    """Inertia tensor (3, 3), kg·m², about the centroid, axes of the vertices' frame,
    of the hull of ``vertices`` (K, 3) filled with uniform density and total ``mass`` kg.

    trimesh's ``moment_inertia`` is for density 1 (mass = volume); we rescale by
    ``mass / volume``.  Box w x h x d: diag(m(h²+d²), m(w²+d²), m(w²+h²)) / 12.
    """
    mesh = convex_hull_mesh(vertices)
    return np.asarray(mesh.moment_inertia, float) * (float(mass) / float(mesh.volume))


def box_vertices_3d(extents) -> np.ndarray:
    """The 8 corners (8, 3) of a box with side lengths ``extents`` = (w, h, d) m along
    x, y, z, centred at the origin."""
    e = np.asarray(extents, float).reshape(-1)
    if e.shape != (3,) or not np.all(e > 0):
        raise TacestError(f"box extents must be three numbers > 0, got {extents}")
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    return 0.5 * signs * e


def sample_polytope_surface(vertices, n: int, seed=None, return_weights=False):
    """About ``n`` points spread uniformly by area over the hull's surface.

    vertices : (K, 3), m.  Returns points (M, 3), m, and with ``return_weights`` also
    weights (M,) summing to 1 (each point's share of the area).

    Default (``seed=None``): deterministic quadrature.  Triangle i of the hull (area
    a_i of total S) is split into m_i² congruent sub-triangles, m_i = round(sqrt(n
    a_i / S)) >= 1, and the sub-triangles' centroids are the points, weighted
    a_i / (m_i² S).  That is a midpoint-type rule: exact for linear functions and with
    error O(h²) for smooth ones (h = sub-triangle size), unlike random samples whose
    error falls only as 1/sqrt(n).  M is close to n, not exactly n.

    With an integer ``seed``: exactly n random points (``trimesh.sample.sample_surface``
    with that seed), equal weights.
    """
    mesh = convex_hull_mesh(vertices)
    n = int(n)
    if n < 1:
        raise TacestError(f"number of samples must be >= 1, got {n}")
    if seed is not None:
        import trimesh

        pts, _ = trimesh.sample.sample_surface(mesh, n, seed=int(seed))
        pts = np.asarray(pts, float)
        w = np.full(pts.shape[0], 1.0 / pts.shape[0])
        return (pts, w) if return_weights else pts
    tri = np.asarray(mesh.triangles, float)  # (M, 3, 3)
    area = np.asarray(mesh.area_faces, float)
    S = float(area.sum())
    m = np.maximum(1, np.rint(np.sqrt(n * area / S))).astype(int)
    pts, wts = [], []
    for mi in np.unique(m):
        uv = _subtriangle_centroids(int(mi))  # (mi², 2)
        sel = m == mi
        T = tri[sel]
        P = T[:, None, 0] + uv[None, :, :1] * (T[:, None, 1] - T[:, None, 0]) \
            + uv[None, :, 1:] * (T[:, None, 2] - T[:, None, 0])
        pts.append(P.reshape(-1, 3))
        wts.append(np.repeat(area[sel] / (mi * mi * S), mi * mi))
    pts = np.concatenate(pts)
    w = np.concatenate(wts)
    w = w / w.sum()
    return (pts, w) if return_weights else pts


def _subtriangle_centroids(m: int) -> np.ndarray:
    """Barycentric (u, v) of the centroids of the m² congruent sub-triangles of the
    reference triangle {u, v >= 0, u + v <= 1}: (m², 2)."""
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    i, j = i.ravel(), j.ravel()
    up = i + j <= m - 1
    down = i + j <= m - 2
    uv_up = np.stack([i[up] + 1.0 / 3.0, j[up] + 1.0 / 3.0], 1)
    uv_dn = np.stack([i[down] + 2.0 / 3.0, j[down] + 2.0 / 3.0], 1)
    return np.concatenate([uv_up, uv_dn]) / m


class PolytopeSurface:
    """The hull surface of a convex polytope, ready for many distance queries.

    vertices : (K, 3) float, m.  Holds the hull's triangles (M, 3, 3), their unit
    outward normals (M, 3) and the unique edges (E, 2, 3).
    """

    def __init__(self, vertices):
        mesh = convex_hull_mesh(vertices)
        self.mesh = mesh
        self.triangles = np.asarray(mesh.triangles, float)
        self.normals = np.asarray(mesh.face_normals, float)
        edges = np.asarray(mesh.edges_unique, int)
        self.edges = np.asarray(mesh.vertices, float)[edges]  # (E, 2, 3)
        self.vertices = np.asarray(mesh.vertices, float)
        # precomputed in-plane barycentric data per triangle
        T = self.triangles
        self._o = T[:, 0]
        self._e1 = T[:, 1] - T[:, 0]
        self._e2 = T[:, 2] - T[:, 0]
        d11 = np.sum(self._e1 * self._e1, 1)
        d12 = np.sum(self._e1 * self._e2, 1)
        d22 = np.sum(self._e2 * self._e2, 1)
        den = d11 * d22 - d12 * d12
        self._good = den > 0  # skip zero-area slivers: their edges still count
        den = np.where(self._good, den, 1.0)
        self._d11, self._d12, self._d22, self._den = d11, d12, d22, den

    def closest(self, points):
        """Exact closest boundary points.

        points : (N, 3), m.  Returns dist (N,) m, closest (N, 3) m.
        The closest point of the surface is either the projection onto a face plane
        (when it lies inside that triangle) or the closest point of an edge; we take
        the best of all those candidates.  O(N (M + E)), chunked.
        """
        P = np.asarray(points, float).reshape(-1, 3)
        dist = np.empty(P.shape[0])
        close = np.empty_like(P)
        chunk = max(1, 1_000_000 // (self.triangles.shape[0] + self.edges.shape[0]))
        for s in range(0, P.shape[0], chunk):
            dist[s:s + chunk], close[s:s + chunk] = self._closest(P[s:s + chunk])
        return dist, close

    def distance(self, points) -> np.ndarray:
        """Exact distance (N,) m from points (N, 3) to the surface."""
        return self.closest(points)[0]

    def _closest(self, P):
        # face candidates: plane projections that fall inside their triangle
        r = P[:, None, :] - self._o[None]  # (N, M, 3)
        h = np.einsum("nmk,mk->nm", r, self.normals)
        q = r - h[..., None] * self.normals[None]
        b1 = np.einsum("nmk,mk->nm", q, self._e1)
        b2 = np.einsum("nmk,mk->nm", q, self._e2)
        u = (self._d22 * b1 - self._d12 * b2) / self._den
        v = (self._d11 * b2 - self._d12 * b1) / self._den
        inside = (u >= 0) & (v >= 0) & (u + v <= 1) & self._good[None]
        fd = np.where(inside, np.abs(h), np.inf)
        fi = np.argmin(fd, axis=1)
        fbest = fd[np.arange(P.shape[0]), fi]
        # edge candidates
        a = self.edges[None, :, 0]
        d = self.edges[None, :, 1] - a
        dd = np.sum(d * d, -1)
        t = np.clip(np.sum((P[:, None] - a) * d, -1) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
        c = a + t[..., None] * d  # (N, E, 3)
        ed = np.linalg.norm(P[:, None] - c, axis=-1)
        ei = np.argmin(ed, axis=1)
        n_idx = np.arange(P.shape[0])
        ebest = ed[n_idx, ei]
        use_face = fbest < ebest
        closest = np.where(use_face[:, None],
                           P - (h[n_idx, fi])[:, None] * self.normals[fi],
                           c[n_idx, ei])
        return np.minimum(fbest, ebest), closest


def polytope_boundary_distance(points, vertices) -> np.ndarray:
    """Exact distance (N,) m from points (N, 3) to the hull surface of ``vertices``."""
    return PolytopeSurface(vertices).distance(points)

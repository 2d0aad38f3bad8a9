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

    Default (``seed=None``): deterministic quadrature, see :func:`surface_lattice`:
    the centroids of congruent sub-triangles ("cells"), weighted by area.  That is a
    midpoint-type rule: exact for linear functions and with error O(h²) for smooth
    ones (h = cell size), unlike random samples whose error falls only as 1/sqrt(n).
    M is close to n, not exactly n.

    With an integer ``seed``: exactly n random points (``trimesh.sample.sample_surface``
    with that seed), equal weights.
    """
    n = int(n)
    if n < 1:
        raise TacestError(f"number of samples must be >= 1, got {n}")
    if seed is not None:
        import trimesh

        pts, _ = trimesh.sample.sample_surface(convex_hull_mesh(vertices), n, seed=int(seed))
        pts = np.asarray(pts, float)
        w = np.full(pts.shape[0], 1.0 / pts.shape[0])
        return (pts, w) if return_weights else pts
    lat = surface_lattice(vertices, n)
    return (lat.points, lat.weights) if return_weights else lat.points


class SurfaceLattice:
    """A quadrature lattice on a triangulated surface (see :func:`surface_lattice`).

    nodes (V, 3) m: lattice vertices; cells (M, 3) int: corner node indices of each
    cell; points (M, 3) m: cell centroids; weights (M,): area shares, sum 1;
    size (M,) m: longest cell edge.
    """

    def __init__(self, nodes, cells, weights):
        self.nodes = nodes
        self.cells = cells
        self.weights = weights
        corners = nodes[cells]  # (M, 3, 3)
        self.points = corners.mean(axis=1)
        self.size = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)

    def sub_points(self, k: int) -> np.ndarray:
        """Centroids (M, k², 3) of the k² congruent sub-cells of every cell."""
        corners = self.nodes[self.cells]
        return subdivide_triangles(corners, k).mean(axis=2)


def surface_lattice(vertices, n: int) -> SurfaceLattice:
    """Split the hull's surface into about ``n`` cells of nearly equal area.

    Triangle i of the hull (area a_i of total S) is split into m_i² congruent
    sub-triangles, m_i = round(sqrt(n a_i / S)) >= 1, each weighted a_i / (m_i² S)
    (weights renormalised to sum to 1).  Lattice nodes are not shared between hull
    triangles.
    """
    mesh = convex_hull_mesh(vertices)
    tri = np.asarray(mesh.triangles, float)  # (T, 3, 3)
    area = np.asarray(mesh.area_faces, float)
    S = float(area.sum())
    m = np.maximum(1, np.rint(np.sqrt(max(1, int(n)) * area / S))).astype(int)
    nodes, cells, wts = [], [], []
    base = 0
    for mi in np.unique(m):
        sel = np.flatnonzero(m == mi)
        uv, idx = _lattice(int(mi))  # (P, 2) node coordinates, (mi², 3) cells
        T = tri[sel]
        P = T[:, None, 0] + uv[None, :, :1] * (T[:, None, 1] - T[:, None, 0]) \
            + uv[None, :, 1:] * (T[:, None, 2] - T[:, None, 0])  # (t, P, 3)
        nodes.append(P.reshape(-1, 3))
        offs = base + uv.shape[0] * np.arange(len(sel))
        cells.append((idx[None] + offs[:, None, None]).reshape(-1, 3))
        wts.append(np.repeat(area[sel] / (mi * mi * S), mi * mi))
        base += uv.shape[0] * len(sel)
    w = np.concatenate(wts)
    return SurfaceLattice(np.concatenate(nodes), np.concatenate(cells), w / w.sum())


def _lattice(m: int):
    """Nodes (u, v) = (i/m, j/m), i + j <= m, of the reference triangle and the corner
    indices (m², 3) of its m² congruent cells ("upward" cells first)."""
    ij = [(i, j) for i in range(m + 1) for j in range(m + 1 - i)]
    index = {p: k for k, p in enumerate(ij)}
    up = [(index[i, j], index[i + 1, j], index[i, j + 1]) for i in range(m) for j in range(m - i)]
    down = [(index[i + 1, j + 1], index[i, j + 1], index[i + 1, j])
            for i in range(m - 1) for j in range(m - 1 - i)]
    return np.array(ij, float) / m, np.array(up + down, int).reshape(-1, 3)


def subdivide_triangles(triangles, m: int) -> np.ndarray:
    """Split each triangle (T, 3, 3) into m² congruent sub-triangles: (T, m², 3, 3)."""
    uv, idx = _lattice(int(m))
    bary = np.concatenate([1.0 - uv.sum(1, keepdims=True), uv], 1)[idx]  # (m², 3, 3)
    return np.einsum("skc,tcd->tskd", bary, np.asarray(triangles, float))


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

"""Simulated objects (3-D): boxes, random convex polytopes, polytopes from a file.

An object is a rigid convex polytope (the convex hull of its vertices) with its
vertices in the body frame, whose origin is the centre of mass (COM).  With uniform
density the COM is the volume centroid; the ``com_offset`` effect moves it (see
:func:`apply_com_offset`).

``--object`` forms with ``--dim 3`` (all lengths in m):

- ``box``: three random extents, each U(0.06, 0.14); ``box:W,H,D``: extents along the
  body x, y, z axes, resting with z up;
- ``polytope`` (or ``polygon``): the convex hull of U{6..12} random points, each a
  hull vertex; ``polytope:K`` (``polygon:K``): K vertices (4..30); diameter
  U(0.06, 0.14);
- a path to a file of vertices: text with one ``x y z`` (or ``x,y,z``) row per vertex
  and ``#`` comments, or JSON: a list of ``[x, y, z]`` or ``{"vertices": [...]}``.
  Any frame; interior points are an error (tacest objects are convex).  Its body frame
  is the file's frame moved to the volume centroid.

Faces.  A face is a maximal planar piece of the hull (the 6 sides of a box, the
triangles of a random polytope).  :func:`hull_faces` lists them in a fixed order that
depends on the shape only, not on the order of the vertices: sorted by their outward
unit normal (x, then y, then z component, rounded to 1e-6).  ``face_friction`` values
and resting faces refer to that order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tacest.errors import TacestError
from tacest.geometry.polytope import box_vertices_3d, convex_hull_mesh, polytope_centroid, polytope_inertia
from tacest.geometry.transforms import quat_from_axis_angle, quat_multiply, quat_to_matrix
from tacest.sim.objects import (FRICTION_FINGER_RANGE, FRICTION_GROUND_RANGE, MASS_RANGE, SIZE_LIMITS, SIZE_RANGE,
                                read_polygon_file)

#: Random polytope vertex counts (inclusive).
POLYTOPE_K_RANGE = (6, 12)
#: Vertex counts accepted in ``polytope:K``.
POLYTOPE_K_LIMITS = (4, 30)
#: Two hull triangles are one face when their unit normals differ by less than this
#: (1e-7 rad: far above float rounding of a hull of ~0.1 m, far below a real edge)
COPLANAR_TOL = 1e-7
#: a vertex farther than this fraction of the object's extent inside the hull is an
#: interior point (not convex); as tacest.sim.objects.NONCONVEX_REL_TOL
NONCONVEX_REL_TOL = 1e-9
#: a face is a stable resting face when the COM projects into the face shrunk by this
#: fraction towards its centroid (the 2-D recorder: the middle 90 % of a face)
STABLE_MARGIN = 0.1


@dataclass
class SimObject3:
    """A rigid convex polytope with its physical parameters.

    vertices : (K, 3) float, m, body frame (origin at the COM), every one a hull vertex;
    mass : kg; inertia : (3, 3) kg·m² about the COM, body axes; friction_ground,
    friction_finger : Coulomb coefficients of the object against the ground and
    against a fingertip; shape : ``"box"`` or ``"polytope"`` (/prior attrs ``shape``).
    """

    vertices: np.ndarray
    mass: float
    inertia: np.ndarray
    friction_ground: float
    friction_finger: float
    shape: str = "polytope"

    def __post_init__(self):
        self._faces = None
        self._centroid = None

    @property
    def faces(self) -> "HullFaces":
        if self._faces is None:
            self._faces = hull_faces(self.vertices)
        return self._faces

    @property
    def n_faces(self) -> int:
        return self.faces.n

    @property
    def centroid__body(self) -> np.ndarray:
        """(3,) m, the volume centroid in the body frame (zero unless the COM is offset)."""
        if self._centroid is None:
            self._centroid = polytope_centroid(self.vertices)
        return self._centroid


# ---------------------------------------------------------------------------------
# polytope geometry


@dataclass
class HullFaces:
    """The faces of a convex hull (module docstring for their order).

    normals : (n, 3) unit outward normals; offsets : (n,) m, so that the face plane is
    ``normals[i] · p = offsets[i]`` and the solid is ``normals · p <= offsets``;
    vertices : list of n index arrays into the vertex array, each face's corners in
    counter-clockwise order seen from outside.
    """

    normals: np.ndarray
    offsets: np.ndarray
    vertices: list

    @property
    def n(self) -> int:
        return int(len(self.offsets))


def hull_faces(vertices) -> HullFaces:
    """The faces (HullFaces) of the convex hull of ``vertices`` (K, 3), m."""
    from scipy.spatial import ConvexHull

    V = np.asarray(vertices, float)
    hull = ConvexHull(V)
    eq = hull.equations  # (M, 4): n·p + b <= 0 inside, n outward unit
    groups = []  # [normal, offset, set of vertex indices]
    for tri, e in zip(hull.simplices, eq):
        for g in groups:
            if np.linalg.norm(g[0] - e[:3]) < COPLANAR_TOL:
                g[2].update(int(i) for i in tri)
                break
        else:
            groups.append([e[:3].copy(), -float(e[3]), set(int(i) for i in tri)])
    keys = np.round(np.array([g[0] for g in groups]), 6)
    order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
    normals, offsets, corners = [], [], []
    for i in order:
        n, o, idx = groups[i]
        idx = np.array(sorted(idx))
        # counter-clockwise about the outward normal
        c = V[idx].mean(axis=0)
        u = V[idx[0]] - c
        u /= np.linalg.norm(u)
        w = np.cross(n, u)
        ang = np.arctan2((V[idx] - c) @ w, (V[idx] - c) @ u)
        normals.append(n / np.linalg.norm(n))
        offsets.append(o)
        corners.append(idx[np.argsort(ang)])
    return HullFaces(np.array(normals), np.array(offsets), corners)


def inradius(vertices, point=None) -> float:
    """m, distance from ``point`` (3,) (default: the volume centroid) to the nearest
    face plane of the hull of ``vertices`` (K, 3); negative when the point is outside."""
    f = hull_faces(vertices)
    p = polytope_centroid(vertices) if point is None else np.asarray(point, float)
    return float(np.min(f.offsets - f.normals @ p))


def check_convex(points, what="polytope") -> np.ndarray:
    """The hull vertices (K', 3) of the points (K, 3), in their given order, after
    checking that no point lies inside the hull (a non-convex shape) and that they span
    a volume; points on a face or an edge are dropped (as collinear points in 2-D).
    TacestError naming ``what`` otherwise."""
    from scipy.spatial import ConvexHull

    p = np.asarray(points, float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 4:
        raise TacestError(f"{what}: needs at least 4 vertices with x, y and z")
    try:
        convex_hull_mesh(p)
    except TacestError as exc:
        raise TacestError(f"{what}: {exc}") from None
    f = hull_faces(p)
    scale = float(np.max(np.ptp(p, axis=0)))
    depth = np.min(f.offsets[None, :] - p @ f.normals.T, axis=1)  # distance inside, per point
    inside = depth > NONCONVEX_REL_TOL * scale
    if np.any(inside):
        i = int(np.argmax(inside))
        raise TacestError(f"{what}: not convex (vertex {i} at {p[i].tolist()} is inside the hull); "
                          "tacest objects are convex")
    return p[np.sort(ConvexHull(p).vertices)]


def random_polytope(rng: np.random.Generator, k: int) -> np.ndarray:
    """(k, 3) a random convex polytope with exactly k vertices, centred at its volume
    centroid.

    k well-spread directions (farthest-point choice among 40·k random unit vectors,
    so no two vertices crowd together), on an ellipsoid with axes U(0.7, 1.3) (every
    point of an ellipsoid is a hull vertex), rotated at random, scaled to a diameter of
    U(0.06, 0.14) m.
    """
    cand = rng.normal(size=(40 * k, 3))
    cand /= np.linalg.norm(cand, axis=1, keepdims=True)
    chosen = [0]
    d = np.linalg.norm(cand - cand[0], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(cand - cand[i], axis=1))
    pts = cand[chosen] * rng.uniform(0.7, 1.3, size=3)
    q = rng.normal(size=4)
    pts = pts @ quat_to_matrix(q / np.linalg.norm(q)).T
    diameter = np.max(np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1))
    pts *= rng.uniform(*SIZE_RANGE) / diameter
    pts = check_convex(pts, "random polytope")
    return pts - polytope_centroid(pts)


def _check_size(vertices, what):
    v = np.asarray(vertices, float)
    size = float(np.max(np.linalg.norm(v[:, None, :] - v[None, :, :], axis=-1)))
    lo, hi = SIZE_LIMITS
    if not lo <= size <= hi:
        raise TacestError(f"{what}: object size {size:.4g} m is outside [{lo}, {hi}] m (lengths are in metres)")


# ---------------------------------------------------------------------------------
# object specs


def make_shape(spec: str, rng: np.random.Generator):
    """The shape named by an ``--object`` spec (module docstring).

    Returns ``(vertices (K, 3) m, centred at the volume centroid; kind "box"|"polytope";
    random_rest)``: random_rest is False when the object rests on the face nearest to
    its given orientation (box, file), True for a random stable face and yaw.
    """
    spec = str(spec).strip()
    head, _, rest = spec.partition(":")
    if head == "box":
        if rest:
            try:
                dims = [float(s) for s in rest.split(",")]
            except ValueError:
                raise TacestError(f"--object {spec}: expected box:W,H,D in metres") from None
            if len(dims) != 3:
                raise TacestError(f"--object {spec}: a 3-D box takes three extents, box:W,H,D (m)")
            if not all(math.isfinite(d) and d > 0 for d in dims):
                raise TacestError(f"--object {spec}: extents must be positive numbers")
            v = box_vertices_3d(dims)
        else:
            v = box_vertices_3d(rng.uniform(*SIZE_RANGE, size=3))
        _check_size(v, f"--object {spec}")
        return v, "box", False
    if head in ("polytope", "polygon"):
        if rest:
            try:
                k = int(rest)
            except ValueError:
                raise TacestError(f"--object {spec}: expected {head}:K with an integer K") from None
            lo, hi = POLYTOPE_K_LIMITS
            if not lo <= k <= hi:
                raise TacestError(f"--object {spec}: K must be in {lo}..{hi} in 3-D")
        else:
            k = int(rng.integers(POLYTOPE_K_RANGE[0], POLYTOPE_K_RANGE[1] + 1))
        return random_polytope(rng, k), "polytope", True
    path = Path(spec)
    if not path.exists():
        raise TacestError(f"--object {spec}: not box, box:W,H,D, polytope, polytope:K or an existing file")
    if path.is_dir():
        raise TacestError(f"--object {spec}: is a folder, expected a file of vertices")
    v = check_convex(read_polygon_file(path, dim=3), what=str(path))
    _check_size(v, str(path))
    return v - polytope_centroid(v), "polytope", False


def uniform_object(vertices, kind, rng: np.random.Generator) -> SimObject3:
    """A uniform-density object of the given shape with random mass and frictions.

    vertices : (K, 3) m, centred at the volume centroid.  Draws (as in 2-D) mass ~
    U(0.1, 1) kg, friction_ground ~ U(0.2, 0.8), friction_finger ~ U(0.1, 0.6); the
    inertia is that of the hull filled uniformly (tacest.geometry.polytope).
    """
    mass = float(rng.uniform(*MASS_RANGE))
    fg = float(rng.uniform(*FRICTION_GROUND_RANGE))
    ff = float(rng.uniform(*FRICTION_FINGER_RANGE))
    return SimObject3(vertices=np.asarray(vertices, float), mass=mass, inertia=polytope_inertia(vertices, mass),
                      friction_ground=fg, friction_finger=ff, shape=kind)


def apply_com_offset(obj: SimObject3, offset) -> SimObject3:
    """The same object with its COM at ``offset`` (3,) m in its current body frame.

    The vertices move by -offset (they stay in the COM frame); the inertia about the
    COM is kept (as in 2-D, docs/effects.md).  A COM outside the shape is a TacestError.
    """
    d = np.asarray(offset, float).reshape(3)
    if inradius(obj.vertices, point=d) <= 0:
        raise TacestError(f"effect com_offset: {d.tolist()} m is outside the object")
    return SimObject3(vertices=obj.vertices - d, mass=obj.mass, inertia=np.array(obj.inertia, float),
                      friction_ground=obj.friction_ground, friction_finger=obj.friction_finger, shape=obj.shape)


# ---------------------------------------------------------------------------------
# resting


def stable_faces(vertices) -> np.ndarray:
    """Indices (into :func:`hull_faces`) of the faces the object can rest on: the COM
    (the body origin) projects into the face shrunk by STABLE_MARGIN towards its
    vertex mean."""
    V = np.asarray(vertices, float)
    f = hull_faces(V)
    out = []
    for i in range(f.n):
        n = f.normals[i]
        p = f.offsets[i] * n  # the origin projected onto the face plane
        corners = V[f.vertices[i]]
        c = corners.mean(axis=0)
        e = np.roll(corners, -1, axis=0) - corners
        inward = np.cross(n, e)  # in-plane, pointing into the (counter-clockwise) face
        inward /= np.linalg.norm(inward, axis=1, keepdims=True)
        d_p = np.sum((p - corners) * inward, axis=1)
        d_c = np.sum((c - corners) * inward, axis=1)
        if np.all(d_p >= STABLE_MARGIN * d_c):
            out.append(i)
    return np.array(out, int)


def face_down_quat(normal__body) -> np.ndarray:
    """(4,) the smallest rotation (scalar-first quaternion) that turns the body vector
    ``normal__body`` (3,) to point straight down (-z)."""
    n = np.asarray(normal__body, float) / np.linalg.norm(normal__body)
    down = np.array([0.0, 0.0, -1.0])
    axis = np.cross(n, down)
    s, c = np.linalg.norm(axis), float(n @ down)
    if s < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0]) if c > 0 else np.array([0.0, 1.0, 0.0, 0.0])
    return quat_from_axis_angle(axis / s, math.atan2(s, c))


def rest_orientation(vertices, rng: np.random.Generator = None) -> np.ndarray:
    """(4,) quaternion, body to world, in which the object rests stably on a face.

    With ``rng``: a random stable face and a random yaw U(0, 2π) about z.  Without:
    the stable face that needs the smallest rotation from the given orientation, and
    that smallest rotation (a box rests as given, z up).
    """
    f = hull_faces(vertices)
    stable = stable_faces(vertices)
    if stable.size == 0:  # cannot happen for a convex polytope with the COM inside
        stable = np.arange(f.n)
    if rng is None:
        i = int(stable[np.argmin(f.normals[stable, 2])])  # most downward normal
        return face_down_quat(f.normals[i])
    i = int(stable[int(rng.integers(len(stable)))])
    yaw = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), rng.uniform(0.0, 2.0 * math.pi))
    return quat_multiply(yaw, face_down_quat(f.normals[i]))


def resting_pose(vertices, quat, xy=(0.0, 0.0), ground_height=0.0) -> np.ndarray:
    """(7,) [x, y, z, qw, qx, qy, qz] with the lowest vertex on the ground and the COM
    at horizontal position ``xy`` (2,) m."""
    q = np.asarray(quat, float) / np.linalg.norm(quat)
    z = ground_height - float(np.min((np.asarray(vertices, float) @ quat_to_matrix(q).T)[:, 2]))
    return np.concatenate([[float(xy[0]), float(xy[1]), z], q])

"""Simulated objects (2-D): boxes, random convex polygons, polygons from a file.

An object is a rigid convex polygon with its vertices in the body frame, whose origin
is the centre of mass (COM).  With uniform density the COM is the area centroid; the
``com_offset`` effect moves it (see :func:`apply_com_offset`).

``--object`` forms (all lengths in m):

- ``box``: random sides, each U(0.06, 0.14); ``box:W,H``: width W (x) and height H (y)
  at rest;
- ``polygon``: random convex polygon with U{4..8} vertices; ``polygon:K``: K vertices
  (3..16); diameter U(0.06, 0.14);
- a path to a file of vertices (docs/simulation.md): text with one ``x y`` (or ``x,y``)
  row per vertex and ``#`` comments, or JSON: a list of ``[x, y]`` pairs or an object
  ``{"vertices": [[x, y], ...]}``.  Any frame and either orientation; the polygon must
  be convex.  Its body frame is the file's frame moved to the centroid.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tacest.errors import TacestError
from tacest.geometry.polygon import (box_vertices, convex_hull_2d, polygon_boundary_distance,
                                     polygon_centroid, polygon_inertia)
from tacest.geometry.transforms import rot2, wrap_angle


#: Random box sides and random polygon diameters, m (the issue: 6-14 cm).
SIZE_RANGE = (0.06, 0.14)
#: Random polygon vertex counts (inclusive).
POLYGON_K_RANGE = (4, 8)
#: Vertex counts accepted in ``polygon:K``.
POLYGON_K_LIMITS = (3, 16)
#: Random mass, kg (uniform density: the inertia follows the shape).
MASS_RANGE = (0.1, 1.0)
#: Random ground and finger friction coefficients.
FRICTION_GROUND_RANGE = (0.2, 0.8)
FRICTION_FINGER_RANGE = (0.1, 0.6)
#: Object sizes accepted from a spec or a file, m: below 5 mm the 1e-4 m contact slop
#: is no longer small; above 0.3 m it breaks the size bound written to /prior.
SIZE_LIMITS = (0.005, 0.3)
#: a vertex farther than this fraction of the object's extent inside the hull makes a
#: file's polygon non-convex (1e-9: far above float rounding of coordinates given to
#: ~15 digits, far below any intended dent)
NONCONVEX_REL_TOL = 1e-9


@dataclass
class SimObject:
    """A rigid convex polygon with its physical parameters.

    vertices : (K, 2) float, m, body frame (origin at the COM), counter-clockwise;
    mass : kg; inertia : kg·m² about the COM; friction_ground, friction_finger : Coulomb
    coefficients of the object against the ground and against a fingertip;
    shape : ``"box"`` or ``"polygon"`` (what /prior attrs ``shape`` says).
    """

    vertices: np.ndarray
    mass: float
    inertia: float
    friction_ground: float
    friction_finger: float
    shape: str = "polygon"

    @property
    def n_faces(self) -> int:
        return int(len(self.vertices))

    @property
    def centroid__body(self) -> np.ndarray:
        """(2,) m, the area centroid in the body frame (zero unless the COM is offset)."""
        return polygon_centroid(self.vertices)

    @property
    def face_normals__body(self) -> np.ndarray:
        """(K, 2) unit outward normals; face i runs from vertex i to vertex i+1."""
        return face_normals(self.vertices)


# ---------------------------------------------------------------------------------
# polygon geometry


def face_normals(vertices) -> np.ndarray:
    """(K, 2) unit outward normals of a counter-clockwise polygon; face i = (v_i, v_i+1)."""
    v = np.asarray(vertices, float)
    e = np.roll(v, -1, axis=0) - v
    n = np.stack([e[:, 1], -e[:, 0]], axis=1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def inradius(vertices, point=None) -> float:
    """m, distance from ``point`` (default: the centroid) to the nearest face line."""
    v = np.asarray(vertices, float)
    p = polygon_centroid(v) if point is None else np.asarray(point, float)
    return float(np.min(np.sum((v - p) * face_normals(v), axis=1)))


def convex_ccw(points, what="polygon") -> np.ndarray:
    """The points as a counter-clockwise convex polygon (tacest.geometry's hull: starts
    at the lowest-x vertex, collinear points dropped).

    A point inside the hull (a non-convex polygon), fewer than 3 points or no area is a
    TacestError naming ``what``.
    """
    p = np.asarray(points, float)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3:
        raise TacestError(f"{what}: needs at least 3 vertices with x and y")
    try:
        hull = convex_hull_2d(p)
    except TacestError as exc:
        raise TacestError(f"{what}: {exc}") from None
    # every given vertex must be on the hull's boundary (up to rounding, relative to size)
    inside = polygon_boundary_distance(p, hull) > NONCONVEX_REL_TOL * float(np.max(np.ptp(p, axis=0)))
    if np.any(inside):
        i = int(np.argmax(inside))
        raise TacestError(f"{what}: not convex (vertex {i} at {p[i].tolist()} is inside the hull); "
                          "tacest objects are convex")
    return hull


def random_polygon(rng: np.random.Generator, k: int) -> np.ndarray:
    """(k, 2) a random convex polygon with exactly k vertices, centred at its centroid.

    Vertices on a circle at random angle gaps (no gap below a third of the largest),
    stretched along x by U(0.7, 1.3) (an affine map keeps convexity and the vertex
    count), rotated at random, scaled to a diameter of U(0.06, 0.14) m.
    """
    gaps = rng.uniform(0.5, 1.5, size=k)
    angles = rng.uniform(0, 2 * math.pi) + 2 * math.pi * np.cumsum(gaps) / np.sum(gaps)
    pts = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    pts[:, 0] *= rng.uniform(0.7, 1.3)
    a = rng.uniform(0, 2 * math.pi)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    pts = pts @ rot.T
    diameter = np.max(np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1))
    pts *= rng.uniform(*SIZE_RANGE) / diameter
    pts = convex_ccw(pts)
    return pts - polygon_centroid(pts)


def read_polygon_file(path, dim: int = 2) -> np.ndarray:
    """(K, dim) vertices from a text or JSON file (module docstring), m, as stored.

    dim : 2 (rows ``x y``) or 3 (rows ``x y z``, for tacest.sim3d).
    """
    path = Path(path)
    xyz = " ".join("xyz"[:dim])
    count = {2: "two", 3: "three"}[dim]
    try:
        text = path.read_text()
    except OSError as exc:
        raise TacestError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise TacestError(f"{path}: not a text file of vertices") from None
    stripped = text.lstrip()
    if path.suffix.lower() == ".json" or stripped.startswith(("[", "{")):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise TacestError(f"{path}: not valid JSON (line {exc.lineno})") from None
        if isinstance(data, dict):
            if "vertices" not in data:
                raise TacestError(f"{path}: JSON object needs a 'vertices' list")
            data = data["vertices"]
        try:
            pts = np.asarray(data, float)
        except (TypeError, ValueError):
            raise TacestError(f"{path}: vertices must be a list of [{xyz.replace(' ', ', ')}] numbers") from None
    else:
        rows = []
        for lineno, line in enumerate(text.splitlines(), 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            fields = line.replace(",", " ").split()
            try:
                row = [float(s) for s in fields]
            except ValueError:
                raise TacestError(f"{path}: line {lineno}: expected {count} numbers '{xyz}', got {line!r}") from None
            if len(row) != dim:
                raise TacestError(f"{path}: line {lineno}: expected {count} numbers '{xyz}', got {len(row)}")
            rows.append(row)
        pts = np.asarray(rows, float).reshape(-1, dim)
    if pts.ndim != 2 or pts.shape[1] != dim:
        raise TacestError(f"{path}: vertices must be rows of {count} numbers ({xyz}), got shape {pts.shape}")
    return pts


def _check_size(vertices, what):
    v = np.asarray(vertices, float)
    size = float(np.max(np.linalg.norm(v[:, None, :] - v[None, :, :], axis=-1)))
    lo, hi = SIZE_LIMITS
    if not lo <= size <= hi:
        raise TacestError(f"{what}: object size {size:.4g} m is outside [{lo}, {hi}] m (lengths are in metres)")


# ---------------------------------------------------------------------------------
# object specs


def make_shape(spec: str, rng: np.random.Generator):
    """The shape named by an ``--object`` spec.

    Returns ``(vertices (K, 2) m, centred at the centroid, CCW; kind "box"|"polygon";
    preferred rest angle or None for a random stable face)``.
    """
    spec = str(spec).strip()
    head, _, rest = spec.partition(":")
    if head == "box":
        if rest:
            try:
                dims = [float(s) for s in rest.split(",")]
            except ValueError:
                raise TacestError(f"--object {spec}: expected box:W,H in metres") from None
            if len(dims) != 2:
                raise TacestError(f"--object {spec}: a 2-D box takes two sides, box:W,H (m)")
            if not all(math.isfinite(d) and d > 0 for d in dims):
                raise TacestError(f"--object {spec}: sides must be positive numbers")
            v = box_vertices(*dims)
        else:
            v = box_vertices(rng.uniform(*SIZE_RANGE), rng.uniform(*SIZE_RANGE))
        _check_size(v, f"--object {spec}")
        return v, "box", 0.0
    if head == "polygon":
        if rest:
            try:
                k = int(rest)
            except ValueError:
                raise TacestError(f"--object {spec}: expected polygon:K with an integer K") from None
            lo, hi = POLYGON_K_LIMITS
            if not lo <= k <= hi:
                raise TacestError(f"--object {spec}: K must be in {lo}..{hi}")
        else:
            k = int(rng.integers(POLYGON_K_RANGE[0], POLYGON_K_RANGE[1] + 1))
        return random_polygon(rng, k), "polygon", None
    path = Path(spec)
    if not path.exists():
        raise TacestError(f"--object {spec}: not box, box:W,H, polygon, polygon:K or an existing file")
    if path.is_dir():
        raise TacestError(f"--object {spec}: is a folder, expected a file of vertices")
    v = convex_ccw(read_polygon_file(path), what=str(path))
    _check_size(v, str(path))
    return v - polygon_centroid(v), "polygon", 0.0


def uniform_object(vertices, kind, rng: np.random.Generator) -> SimObject:
    """A uniform-density object of the given shape with random mass and frictions.

    vertices : (K, 2) m, centred at the centroid.  Draws mass ~ U(0.1, 1) kg,
    friction_ground ~ U(0.2, 0.8), friction_finger ~ U(0.1, 0.6); inertia = m·J/A
    (tacest.geometry.polygon.polygon_inertia).
    """
    mass = float(rng.uniform(*MASS_RANGE))
    fg = float(rng.uniform(*FRICTION_GROUND_RANGE))
    ff = float(rng.uniform(*FRICTION_FINGER_RANGE))
    return SimObject(vertices=np.asarray(vertices, float), mass=mass, inertia=polygon_inertia(vertices, mass),
                     friction_ground=fg, friction_finger=ff, shape=kind)


def apply_com_offset(obj: SimObject, dx: float, dy: float) -> SimObject:
    """The same object with its COM at (dx, dy) in its current body frame.

    The vertices move by -(dx, dy) (they stay in the COM frame); the inertia about the
    COM is kept (docs/effects.md).  A COM outside the shape is a TacestError.
    """
    d = np.array([dx, dy], float)
    if inradius(obj.vertices, point=d) <= 0:
        raise TacestError(f"effect com_offset: ({dx}, {dy}) m is outside the object")
    return SimObject(vertices=obj.vertices - d, mass=obj.mass, inertia=obj.inertia,
                     friction_ground=obj.friction_ground, friction_finger=obj.friction_finger,
                     shape=obj.shape)


def rest_angle(vertices, rng: np.random.Generator, preferred=None) -> float:
    """rad, an orientation in which the object rests stably on a face.

    A face is stable when the COM (the body origin) projects onto its middle 90 %.
    With ``preferred`` the stable orientation nearest to it is chosen, else a random
    stable face.
    """
    v = np.asarray(vertices, float)
    n = face_normals(v)
    e = np.roll(v, -1, axis=0) - v
    t = np.sum(-v * e, axis=1) / np.sum(e * e, axis=1)  # projection of the origin on each face
    stable = np.flatnonzero((t > 0.05) & (t < 0.95))
    if stable.size == 0:  # cannot happen for a convex polygon with the COM inside
        stable = np.arange(len(v))
    # the angle that turns outward normal n_i to point straight down (-y)
    angles = -0.5 * math.pi - np.arctan2(n[stable, 1], n[stable, 0])
    angles = wrap_angle(angles)
    if preferred is None:
        return float(angles[int(rng.integers(len(angles)))])
    diff = np.abs(wrap_angle(angles - preferred))
    return float(angles[int(np.argmin(diff))])


def resting_pose(vertices, angle, x=0.0, ground_height=0.0) -> np.ndarray:
    """(3,) [x, y, angle] with the lowest vertex on the ground, COM at horizontal ``x``."""
    y = ground_height - float(np.min((np.asarray(vertices, float) @ rot2(angle).T)[:, 1]))
    return np.array([x, y, angle], float)

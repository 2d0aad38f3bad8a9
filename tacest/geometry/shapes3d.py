"""3-D shape parameterizations for the estimator (CasADi-symbolic and numeric).

A parameterization maps free shape parameters ``s`` (scaled: lengths in units of the
problem's length scale ``L``) to body-frame vertices (K, 3) of a convex shape.  The body
origin is the centre of mass.

- ``box``: s = [w, d, h] / L, the extents along body x, y, z; vertices (8, 3) =
  (±w/2, ±d/2, ±h/2).  Its signed distance has the closed form of :func:`box_signed_distance`.
- ``polytope:K`` (6 <= K <= 64): s = [r_1 .. r_K] / L > 0, the radii of K support points
  r_k u_k along K fixed unit directions u_k (a Fibonacci lattice on the sphere).  The shape
  is the convex hull of the points, convex by construction for every s; some points may
  fall inside the hull and are then simply never the lowest (they carry no contact).
  Because the directions surround the origin (the hull of the u_k contains a ball of
  radius > 0.3 for K >= 6), the origin, hence the centre of mass, is always inside the
  shape.  The body frame is the one the pose observations define, so the shape need not
  be centred on its own centroid (non-uniform density is allowed).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from tacest.errors import TacestError

#: smallest and largest number of support directions of ``polytope:K``: below 6 the
#: Fibonacci directions need not surround the origin; above 64 the NLP grows for little
POLYTOPE_K_RANGE = (6, 64)
#: smallest extent or radius as a fraction of the size bound (keeps the shape solid)
MIN_SIZE_FRACTION = 0.05


def fibonacci_directions(K: int) -> np.ndarray:
    """K unit vectors (K, 3) spread nearly uniformly over the sphere (golden-angle
    spiral), deterministic."""
    i = np.arange(K) + 0.5
    z = 1.0 - 2.0 * i / K
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * np.arange(K)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


@dataclass
class Shape3D:
    """A 3-D shape parameterization; ``name`` is the SPEC string (``box``, ``polytope:12``)."""

    name: str
    n_vertices: int
    n_params: int
    param_names: list = field(default_factory=list)

    def vertices(self, s, L):
        """Body-frame vertices (K, 3), m, from scaled parameters s (n_params,)."""
        raise NotImplementedError

    def initial(self, extents):
        """Scaled parameters of a starting shape of box extents (3,) (units of L)."""
        raise NotImplementedError

    def params_from_vertices(self, V, L):
        """Scaled parameters (n_params,) of the shape whose body-frame vertices
        (:meth:`vertices`) are V (K, 3) m, e.g. an earlier estimate's (the inverse of
        :meth:`vertices` on its image)."""
        raise NotImplementedError

    def bounds(self, size_bound_scaled):
        """Lower and upper bounds on s (numpy arrays)."""
        return (np.full(self.n_params, MIN_SIZE_FRACTION * size_bound_scaled),
                np.full(self.n_params, size_bound_scaled))

    def signed_distance(self, p_body, s, L):
        """Signed distance (m) from p_body (3,) (body frame, m) to the shape (CasADi)."""
        raise NotImplementedError

    def uniform_cholesky_reference(self, s):
        """Log-Cholesky parameters (6,) of the second moment per unit mass (units of L²)
        of a uniform-density reference body of this shape: the centre of the inertia
        prior (see :mod:`tacest.dynamics.rigid3d`).  CasADi."""
        raise NotImplementedError


class Box3D(Shape3D):
    def __init__(self):
        super().__init__(name="box", n_vertices=8, n_params=3, param_names=["extent_x", "extent_y", "extent_z"])

    def vertices(self, s, L):
        rows = []
        for sx in (-1, 1):
            for sy in (-1, 1):
                for sz in (-1, 1):
                    rows.append(ca.horzcat(sx * s[0], sy * s[1], sz * s[2]) * (L / 2))
        return ca.vertcat(*rows)

    def initial(self, extents):
        return np.asarray(extents, float).reshape(3).copy()

    def params_from_vertices(self, V, L):
        return np.ptp(np.asarray(V, float).reshape(8, 3), axis=0) / L

    def signed_distance(self, p_body, s, L):
        return box_signed_distance(p_body, s * (L / 2))

    def uniform_cholesky_reference(self, s):
        # uniform box: Sigma / m = diag(w², d², h²) / 12
        return ca.vertcat(ca.log(s[0] / np.sqrt(12.0)), ca.log(s[1] / np.sqrt(12.0)),
                          ca.log(s[2] / np.sqrt(12.0)), 0, 0, 0)


class Polytope3D(Shape3D):
    def __init__(self, K: int):
        lo, hi = POLYTOPE_K_RANGE
        if not lo <= K <= hi:
            raise TacestError(f"polytope:K needs {lo} <= K <= {hi}, got {K}")
        super().__init__(name=f"polytope:{K}", n_vertices=K, n_params=K,
                         param_names=[f"radius{k}" for k in range(K)])
        self.directions = fibonacci_directions(K)
        from scipy.spatial import ConvexHull

        hull = ConvexHull(self.directions)
        faces = []
        for simplex, eq in zip(hull.simplices, hull.equations):
            a, b, c = self.directions[simplex]
            if np.dot(np.cross(b - a, c - a), eq[:3]) < 0:  # outward (counter-clockwise) order
                simplex = simplex[[0, 2, 1]]
            faces.append(simplex)
        #: (M, 3) int: the triangulation of the direction hull, outward order; the
        #: finger signed distance uses its faces (see :meth:`signed_distance`)
        self.faces = np.array(faces, int)

    def vertices(self, s, L):
        U = ca.DM(self.directions)
        return ca.vertcat(*[s[k] * L * U[k, :] for k in range(self.n_vertices)])

    def initial(self, extents):
        """Radii putting every support point on the surface of the box of ``extents``."""
        half = 0.5 * np.asarray(extents, float).reshape(3)
        U = np.abs(self.directions)
        return np.min(half[None, :] / np.maximum(U, 1e-12), axis=1)

    def params_from_vertices(self, V, L):
        V = np.asarray(V, float).reshape(self.n_vertices, 3)
        return np.einsum("kc,kc->k", V, self.directions) / L  # V_k = s_k L u_k, |u_k| = 1

    def signed_distance(self, p_body, s, L):
        """Largest signed distance to the planes of the faces of the fixed triangulation
        of the support points: exact inside and on the surface of the shape when that
        triangulation is its hull, a lower bound outside near edges and corners (it is
        used for fingertips in contact, where the gap is ~0)."""
        V = self.vertices(s, L)
        d = None
        for i, j, k in self.faces:
            a, b, c = V[i, :].T, V[j, :].T, V[k, :].T
            n = _cross(b - a, c - a)
            n = n / ca.sqrt(ca.dot(n, n))
            dk = ca.dot(n, p_body - a)
            d = dk if d is None else ca.fmax(d, dk)
        return d

    def uniform_cholesky_reference(self, s):
        # a uniform solid ball of the mean radius r: Sigma / m = r² / 5 · 1
        r = ca.sum1(s) / self.n_vertices
        lr = ca.log(r / np.sqrt(5.0))
        return ca.vertcat(lr, lr, lr, 0, 0, 0)


def _cross(a, b):
    return ca.vertcat(a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def box_signed_distance(p_body, half):
    """Signed distance (m) from a point p_body (3,) (body frame, m) to the box
    [-half, half] (half (3,) m), in closed form: with e = |p| - half,
    sd = |max(e, 0)| outside (the Euclidean distance, C¹) and max_i e_i inside (the
    distance to the nearest face).  Both are 0 on the surface.  CasADi or numpy."""
    e = ca.fabs(p_body) - half
    emax = ca.fmax(e[0], ca.fmax(e[1], e[2]))
    pos = ca.fmax(e, 0)
    outside = ca.sqrt(ca.dot(pos, pos) + 1e-300)
    return ca.if_else(emax > 0, outside, emax)


def shape_sd_and_normal_function(shape: Shape3D):
    """CasADi Function (p_body (3), s (n_params), L) -> (sd (m), n_body (3), the
    gradient of sd: the outward normal at the closest surface point)."""
    p = ca.SX.sym("p_body", 3)
    s = ca.SX.sym("s", shape.n_params)
    L = ca.SX.sym("L")
    sd = shape.signed_distance(p, s, L)
    return ca.Function(f"sd_{shape.name.replace(':', '_')}", [p, s, L], [sd, ca.gradient(sd, p)],
                       ["p_body", "s", "L"], ["sd", "n_body"])


def make_shape_3d(spec: str) -> Shape3D:
    """Parse a SPEC 3-D shape string: ``box`` or ``polytope:K`` (default K = 12)."""
    spec = str(spec).strip().lower()
    if spec == "box":
        return Box3D()
    m = re.fullmatch(r"polytope(?::(\d+))?", spec)
    if m:
        return Polytope3D(int(m.group(1) or 12))
    raise TacestError(f"unknown 3-D shape {spec!r}: use box or polytope:K (e.g. polytope:12)")


def numeric_vertices_3d(shape: Shape3D, s, L) -> np.ndarray:
    """(K, 3) float, m: :meth:`Shape3D.vertices` evaluated numerically."""
    return np.array(ca.DM(shape.vertices(ca.DM(np.asarray(s, float)), float(L))))

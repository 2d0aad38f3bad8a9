"""Shape parameterizations for the estimator (CasADi-symbolic and numeric).

A parameterization maps a vector of free shape parameters ``s`` (scaled, dimensionless:
lengths are in units of the problem's length scale ``L``) to the body-frame vertices of
a convex shape whose origin is its centroid (= centre of mass for uniform density).

2-D shapes:

- ``box``: s = [w, h] / L; vertices (4, 2) = (±w/2, ±h/2), counter-clockwise.
- ``polygon:K``: s = K free vertices u (K, 2) / L, counter-clockwise; the vertices are
  u minus the area centroid of u (so the body origin is the centroid), and convexity
  is kept by the constraints :meth:`Shape.constraints` (every turn left by at least a
  small angle, every edge longer than a minimum), which makes the uniform-density
  inertia valid by construction.

Every symbolic function works on ``casadi.SX``/``MX`` and on numpy (through
``casadi.DM``), so the numeric and symbolic paths share one implementation.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import casadi as ca
import numpy as np

from tacest.errors import TacestError

#: smallest edge length of an estimated polygon, as a fraction of the length scale L:
#: keeps edge normals defined (0.5 mm for a 10 cm object)
MIN_EDGE_FRACTION = 0.005
#: smallest sin(turn angle) at every polygon vertex, keeping it strictly convex; 1e-3
#: allows a nearly straight vertex (0.06°) that is indistinguishable from an edge point
MIN_TURN_SIN = 1e-3


def polygon_area_centroid_j(V):
    """Area, centroid and polar second moment about the centroid of a CCW polygon.

    Parameters
    ----------
    V : (K, 2) casadi SX/MX/DM or numpy, m

    Returns
    -------
    area : scalar, m²;  centroid : (1, 2), m;  J : scalar, m⁴ (∫ |r - c|² dA)
    """
    K = V.shape[0]
    A2 = 0
    cx = 0
    cy = 0
    jo = 0  # polar moment about the origin times 12
    for k in range(K):
        x0, y0 = V[k, 0], V[k, 1]
        x1, y1 = V[(k + 1) % K, 0], V[(k + 1) % K, 1]
        cr = x0 * y1 - x1 * y0
        A2 = A2 + cr
        cx = cx + (x0 + x1) * cr
        cy = cy + (y0 + y1) * cr
        jo = jo + cr * (x0 * x0 + x0 * x1 + x1 * x1 + y0 * y0 + y0 * y1 + y1 * y1)
    area = A2 / 2
    cx = cx / (3 * A2)
    cy = cy / (3 * A2)
    J = jo / 12 - area * (cx * cx + cy * cy)
    return area, ca.horzcat(cx, cy) if isinstance(V, (ca.SX, ca.MX, ca.DM)) else np.array([cx, cy]), J


@dataclass
class Shape:
    """A 2-D shape parameterization.  ``name`` is the SPEC string (``box``, ``polygon:8``)."""

    name: str
    n_vertices: int
    n_params: int

    def vertices(self, s, L):
        """Body-frame vertices (K, 2) in m from scaled parameters s (n_params,)."""
        raise NotImplementedError

    def constraints(self, s):
        """Inequality constraints g(s) >= 0 (list of scalars), dimensionless."""
        return []

    def initial(self, width, height):
        """Scaled parameters of a starting shape of the given extents (in units of L)."""
        raise NotImplementedError

    def bounds(self, size_bound_scaled):
        """Lower and upper bounds on s (numpy arrays)."""
        raise NotImplementedError


class Box2D(Shape):
    def __init__(self):
        super().__init__(name="box", n_vertices=4, n_params=2)

    def vertices(self, s, L):
        w, h = s[0] * L / 2, s[1] * L / 2
        return ca.vertcat(ca.horzcat(-w, -h), ca.horzcat(w, -h), ca.horzcat(w, h), ca.horzcat(-w, h))

    def initial(self, width, height):
        return np.array([width, height], float)

    def bounds(self, size_bound_scaled):
        return np.full(2, 0.05 * size_bound_scaled), np.full(2, size_bound_scaled)


class Polygon2D(Shape):
    def __init__(self, K):
        if not 3 <= K <= 64:
            raise TacestError(f"polygon:K needs 3 <= K <= 64, got {K}")
        super().__init__(name=f"polygon:{K}", n_vertices=K, n_params=2 * K)

    def raw(self, s, L):
        return ca.reshape(s, 2, self.n_vertices).T * L

    def vertices(self, s, L):
        U = self.raw(s, L)
        _, c, _ = polygon_area_centroid_j(U)
        return U - ca.repmat(c, self.n_vertices, 1)

    def constraints(self, s):
        U = self.raw(s, 1.0)
        K = self.n_vertices
        g = []
        for k in range(K):
            e0 = U[(k + 1) % K, :] - U[k, :]
            e1 = U[(k + 2) % K, :] - U[(k + 1) % K, :]
            l0 = ca.sqrt(ca.sumsqr(e0) + 1e-12)
            l1 = ca.sqrt(ca.sumsqr(e1) + 1e-12)
            # sin of the left turn at vertex k+1 minus its minimum (convex, CCW)
            g.append((e0[0] * e1[1] - e0[1] * e1[0]) / (l0 * l1) - MIN_TURN_SIN)
            g.append(l0 - MIN_EDGE_FRACTION)
        return g

    def initial(self, width, height):
        """A K-gon inscribed in the ellipse-ish box of the extents, rotated so that one
        edge lies flat at the bottom (the object rests on a face)."""
        K = self.n_vertices
        ang = -np.pi / 2 - np.pi / K + 2 * np.pi * np.arange(K) / K
        pts = np.stack([np.cos(ang), np.sin(ang)], 1)
        pts = pts / np.abs(pts).max(0)  # span [-1, 1] in x and y
        pts = pts * np.array([width, height]) / 2
        return pts.reshape(-1)  # row-major (x0, y0, x1, y1, ...) = column-major of (2, K)

    def bounds(self, size_bound_scaled):
        b = np.full(self.n_params, size_bound_scaled)
        return -b, b


def make_shape(spec: str, dim: int = 2) -> Shape:
    """Parse a SPEC shape string (``box``, ``polygon:K``)."""
    if dim != 2:
        raise TacestError(f"shape {spec!r}: 3-D estimation is not available in this version")
    spec = spec.strip().lower()
    if spec == "box":
        return Box2D()
    m = re.fullmatch(r"polygon(?::(\d+))?", spec)
    if m:
        return Polygon2D(int(m.group(1) or 8))
    raise TacestError(f"unknown shape {spec!r}: use box or polygon:K (e.g. polygon:8)")


def numeric_vertices(shape: Shape, s, L) -> np.ndarray:
    """Evaluate :meth:`Shape.vertices` numerically: (K, 2) float, m."""
    return np.array(ca.DM(shape.vertices(ca.DM(np.asarray(s, float)), L)))


def rot2(angle):
    """2x2 rotation matrix (body to world) of a CCW angle in rad (casadi or float)."""
    c, s = ca.cos(angle), ca.sin(angle)
    return ca.vertcat(ca.horzcat(c, -s), ca.horzcat(s, c))


def cross2(a, b):
    """z-component of the cross product of two 2-vectors."""
    return a[0] * b[1] - a[1] * b[0]


def signed_distance_polygon(p_body, V, eps=1e-9):
    """Signed distance from a point to a convex CCW polygon, and the outward normal.

    Parameters
    ----------
    p_body : (2,) point, body frame, m
    V : (K, 2) vertices, body frame, m
    eps : m, smoothing of the vertex distance norm (keeps its gradient defined)

    Returns
    -------
    sd : scalar, m (> 0 outside, < 0 inside; exact for a convex polygon)
    n_body : (2,) unit outward normal at the closest boundary point, body frame
        (the gradient of sd with respect to p_body).

    Outside, sd is the distance to the nearest edge segment (C¹ for a convex polygon);
    inside, it is the largest edge-plane distance.  Both agree on the boundary.
    """
    K = V.shape[0]
    d_face = []
    d_seg = []
    for k in range(K):
        a = V[k, :].T
        b = V[(k + 1) % K, :].T
        e = b - a
        le2 = ca.sumsqr(e)
        nu = ca.vertcat(e[1], -e[0]) / ca.sqrt(le2)
        w = p_body - a
        d_face.append(ca.dot(nu, w))
        t = ca.dot(w, e) / le2
        r = w - ca.fmin(ca.fmax(t, 0), 1) * e
        # inside the edge's slab the segment distance is the plane distance (smooth),
        # beyond it the distance to the end vertex
        d_seg.append(ca.if_else(ca.logic_and(t > 0, t < 1), ca.fabs(ca.dot(nu, w)), ca.sqrt(ca.sumsqr(r) + eps**2)))
    dmax = d_face[0]
    dmin = d_seg[0]
    for k in range(1, K):
        dmax = ca.fmax(dmax, d_face[k])
        dmin = ca.fmin(dmin, d_seg[k])
    sd = ca.if_else(dmax > 0, dmin, dmax)
    return sd


def polygon_sd_and_normal_function(K):
    """CasADi Function (p_body (2), V (K, 2)) -> (sd, n_body (2)) built once per K."""
    p = ca.SX.sym("p_body", 2)
    V = ca.SX.sym("V", K, 2)
    sd = signed_distance_polygon(p, V)
    n = ca.gradient(sd, p)
    return ca.Function(f"sd_polygon_{K}", [p, V], [sd, n], ["p_body", "V"], ["sd", "n_body"])


def parse_size(value) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise TacestError(f"size must be a positive number, got {value!r}")
    return v

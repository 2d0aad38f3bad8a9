"""What an estimate says about the object, as a 3-D rigid body other tools can load.

:func:`body_from_estimate` turns an estimate file's content (tacest.io.estimate.Estimate)
into an :class:`ExportBody`: the convex hull mesh of the estimated vertices in the body
frame (origin at the centre of mass, SI units), mass, inertia about the centre of mass
in body axes, ground and finger friction, the effects a simulator can express, the
estimated pose trajectory of one run, and the provenance lines that every exported
file carries in its comment block (what came from where, what the data could not tell).

2-D estimates (SPEC: x horizontal, y up, angle counter-clockwise) become prisms: the
2-D plane is the 3-D x–z plane (z up, as SPEC's 3-D world), the polygon is extruded by
``depth`` m along y, centred on the plane.  A 2-D pose ``[x, y, angle]`` is the 3-D pose
``[x, 0, y, cos(angle/2), 0, -sin(angle/2), 0]`` (counter-clockwise in x–y seen from +z
is a rotation by -angle about +y in x–z).  The depth is an assumption, not an estimate,
and so is the split of the estimated planar inertia into its 3-D components (see
:func:`extruded_inertia`); both are said so in the notes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from tacest.errors import TacestError
from tacest.geometry.polytope import convex_hull_mesh

#: m, default depth of the prism a 2-D estimate is extruded to when none is given: the
#: middle of the simulator's object size range (0.06 to 0.14 m, tacest.sim.objects)
DEFAULT_DEPTH = 0.1
#: MJCF keyframes written by default at most (MuJoCo stores each as a full state; a
#: few hundred seconds at 100 Hz would be tens of thousands)
MAX_KEYFRAMES = 1000

#: estimate /params names of the 2-D effect parameters a simulator can express, and
#: the ExportBody field they go to
_EFFECT_FIELDS = {
    "restitution.e": "restitution",
    "linear_drag.b": "linear_damping",
    "angular_damping.c": "angular_damping",
}


@dataclass
class ExportBody:
    """A rigid body to export (3-D, SI units).

    vertices__body : (K, 3) m, hull vertices, body frame (origin at the centre of mass);
    faces : (M, 3) int, outward-oriented triangles of the convex hull;
    mass : kg; inertia__body : (3, 3) kg·m² about the centre of mass, body axes;
    friction_ground, friction_finger : Coulomb coefficients (object–ground, object–fingertip);
    restitution : coefficient of restitution or None; edge_radius : m, rounded edges
    and corners (the mesh is the outer shape; 0 = sharp); ground_offset : m, height of
    the ground plane above the recording's; linear_damping : N·s/m and angular_damping :
    N·m·s, or None;
    time : (T,) s or None (unknown); pose__world : (T, 7) [x, y, z, qw, qx, qy, qz] of the
    centre of mass, or (0, 7) without a trajectory;
    name : model name; notes : provenance lines for the comment block;
    params : {name: value} of every number exported, for the JSON sidecar.
    """

    vertices__body: np.ndarray
    faces: np.ndarray
    mass: float
    inertia__body: np.ndarray
    friction_ground: float
    friction_finger: float
    restitution: Optional[float] = None
    edge_radius: float = 0.0
    ground_offset: float = 0.0
    linear_damping: Optional[float] = None
    angular_damping: Optional[float] = None
    time: Optional[np.ndarray] = None
    pose__world: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    name: str = "tacest_object"
    notes: list = field(default_factory=list)
    params: dict = field(default_factory=dict)

    def mesh(self):
        """The hull as a ``trimesh.Trimesh`` (body frame, m)."""
        import trimesh

        return trimesh.Trimesh(vertices=self.vertices__body, faces=self.faces, process=False)

    def inner_vertices__body(self) -> np.ndarray:
        """(K, 3) m: the vertices moved inwards by the edge radius along each body axis
        (the inner box that, swept by a ball of radius ``edge_radius``, is the rounded
        box whose outer extents are the estimate's, tacest/estimation/problem3d.py)."""
        if self.edge_radius <= 0:
            return self.vertices__body.copy()
        return self.vertices__body - self.edge_radius * np.sign(self.vertices__body)


# ---------------------------------------------------------------------------------
# 2-D estimates: prisms


def pose2_to_pose3(pose2) -> np.ndarray:
    """(T, 7) 3-D poses of 2-D poses (T, 3) [x, y, angle] (module docstring)."""
    p = np.atleast_2d(np.asarray(pose2, float))
    half = 0.5 * p[:, 2]
    zeros = np.zeros(len(p))
    return np.stack([p[:, 0], zeros, p[:, 1], np.cos(half), zeros, -np.sin(half), zeros], axis=1)


def extrude_polygon(vertices2, depth: float) -> np.ndarray:
    """(2K, 3) m: the prism of the 2-D polygon ``vertices2`` (K, 2) [x, y] m, extruded by
    ``depth`` m along the 3-D y axis, centred on y = 0; 2-D (x, y) is 3-D (x, z)."""
    v = np.asarray(vertices2, float)
    half = 0.5 * float(depth)
    front = np.stack([v[:, 0], np.full(len(v), -half), v[:, 1]], axis=1)
    back = front.copy()
    back[:, 1] = half
    return np.concatenate([front, back])


def extruded_inertia(vertices3, mass: float, inertia_planar: float) -> np.ndarray:
    """(3, 3) kg·m², about the body origin, of a prism (vertices3 (2K, 3) m, from
    :func:`extrude_polygon`) whose inertia about the y axis is the estimated planar one.

    A 2-D estimate knows one number, I_yy = ∫(x² + z²) dm.  Assumptions, said in the
    notes: the density is uniform along the depth (∫y² dm = m d²/12, no products with
    y), and the in-plane second moments ∫x² dm, ∫z² dm, ∫xz dm keep the proportions of
    a uniform-density prism, scaled so that their sum is the estimated I_yy.  With
    S = ∫ p pᵀ dm the inertia is tr(S)·Id − S.
    """
    mesh = convex_hull_mesh(vertices3)
    rho_scale = float(mass) / float(mesh.volume)
    I_c = np.asarray(mesh.moment_inertia, float) * rho_scale  # about the volume centroid
    c = np.asarray(mesh.center_mass, float)
    S_c = 0.5 * np.trace(I_c) * np.eye(3) - I_c  # ∫ (p-c)(p-c)ᵀ dm
    S = S_c + float(mass) * np.outer(c, c)  # about the body origin (the COM)
    planar = S[0, 0] + S[2, 2]
    k = float(inertia_planar) / planar
    S_est = np.zeros((3, 3))
    S_est[0, 0], S_est[2, 2] = k * S[0, 0], k * S[2, 2]
    S_est[0, 2] = S_est[2, 0] = k * S[0, 2]
    S_est[1, 1] = S[1, 1]
    return np.trace(S_est) * np.eye(3) - S_est


# ---------------------------------------------------------------------------------
# from an estimate


def _fmt(v) -> str:
    return f"{float(v):.6g}"


def _certainty(est, name: str) -> str:
    """How far the data determine /params ``name``: a phrase for the notes."""
    ident = est.identifiable.get(name) if isinstance(est.identifiable, dict) else None
    sd = est.std.get(name) if isinstance(est.std, dict) else None
    sd_text = "" if sd is None or not np.isfinite(sd) else f", one sigma {float(sd):.3g}"
    if ident is False:
        return f"NOT IDENTIFIABLE from the data: this is the estimator's prior, not a measurement{sd_text}"
    if ident is True:
        return f"estimated from the data{sd_text}"
    return f"estimated (the file does not say whether the data determine it){sd_text}"


def body_from_estimate(est, depth: Optional[float] = None, run_index: int = 0, time=None,
                       source: str = "") -> ExportBody:
    """An ExportBody of an estimate.

    est : tacest.io.estimate.Estimate; depth : m, prism depth of a 2-D estimate
    (default DEFAULT_DEPTH; an error for a 3-D one); run_index : which estimated run's
    trajectory to carry (``/runs/<i>``; the first by default); time : (T,) s of that run
    (from its run file) or None; source : the estimate's file name for the notes.
    """
    if depth is not None and est.dim == 3:
        raise TacestError(f"{source or 'estimate'}: --depth is for 2-D estimates; this one is 3-D")
    if est.runs and not 0 <= run_index < len(est.runs):
        raise TacestError(f"{source or 'estimate'}: /runs/{run_index}: no such run "
                          f"(the estimate has {len(est.runs)})")
    p = est.params
    src = source or est.filename or "the estimate"
    notes = [
        f"tacest export of {src}: estimate of shape '{est.shape}' (dim {est.dim}), method {est.method}, "
        f"solver status {est.solver_status}, model effects {list(est.model) or 'none'}.",
        "Frame: the body frame has its origin at the estimated centre of mass; SI units (m, kg, s, N).",
    ]
    if est.dim == 3:
        V = np.asarray(est.vertices, float)
        inertia = np.asarray(p["inertia"], float).reshape(3, 3)
        notes.append(f"Geometry: convex hull of the {len(V)} estimated vertices (/params/vertices).")
        notes.append(f"Inertia about the centre of mass, body axes, from /params inertia: "
                     f"{_certainty(est, 'inertia')}.")
    else:
        d = DEFAULT_DEPTH if depth is None else float(depth)
        if not (math.isfinite(d) and d > 0):
            raise TacestError(f"--depth must be a positive length in m, got {depth}")
        V = extrude_polygon(est.vertices, d)
        inertia = extruded_inertia(V, float(p["mass"]), float(p["inertia"]))
        notes.append(f"Geometry: the {len(est.vertices)}-vertex estimated polygon (/params/vertices, 2-D x-y) as "
                     f"the 3-D x-z plane, extruded along y to a depth of {d:.6g} m.")
        notes.append(f"ASSUMPTION: the depth {d:.6g} m is not estimated (2-D data say nothing about it; "
                     f"{'given by --depth' if depth is not None else 'the default, change it with --depth'}).")
        notes.append(f"Inertia: I_yy is the estimated planar inertia {_fmt(p['inertia'])} kg m^2 (/params inertia: "
                     f"{_certainty(est, 'inertia')}). ASSUMPTION: the other components take uniform density "
                     "along the depth and the in-plane proportions of a uniform-density prism.")
    mesh = convex_hull_mesh(V)
    faces = np.asarray(mesh.faces, int)
    V = np.asarray(mesh.vertices, float)
    notes.append(f"mass {_fmt(p['mass'])} kg (/params mass): {_certainty(est, 'mass')}.")
    notes.append(f"friction_ground {_fmt(p['friction_ground'])} (object-ground Coulomb coefficient, "
                 f"/params friction_ground): {_certainty(est, 'friction_ground')}.")
    notes.append(f"friction_finger {_fmt(p['friction_finger'])} (object-fingertip Coulomb coefficient, "
                 f"/params friction_finger): {_certainty(est, 'friction_finger')}.")
    body = ExportBody(vertices__body=V, faces=faces, mass=float(p["mass"]), inertia__body=inertia,
                      friction_ground=float(p["friction_ground"]), friction_finger=float(p["friction_finger"]),
                      notes=notes)
    for key, attr in _EFFECT_FIELDS.items():
        if key in p:
            setattr(body, attr, float(p[key]))
            notes.append(f"{key} {_fmt(p[key])} (/params {key}): {_certainty(est, key)}.")
    if est.dim == 3:
        body.edge_radius = max(float(p.get("edge_radius", 0.0)), 0.0)
        body.ground_offset = float(p.get("ground_offset", 0.0))
        if "edge_radius" in p:
            notes.append(f"edge_radius {_fmt(body.edge_radius)} m (/params edge_radius, edges and corners rounded; "
                         f"the mesh is the outer shape): {_certainty(est, 'edge_radius')}.")
        if "ground_offset" in p:
            notes.append(f"ground_offset {_fmt(body.ground_offset)} m (/params ground_offset, the ground's height "
                         f"above the recording's): {_certainty(est, 'ground_offset')}.")
    other = sorted(k for k in p if k not in ("mass", "inertia", "friction_ground", "friction_finger",
                                            "edge_radius", "ground_offset") and k not in _EFFECT_FIELDS)
    for k in other:
        notes.append(f"{k} (/params {k}) = {np.asarray(p[k]).tolist()}: not a property of the object this format "
                     "can hold; not exported.")
    if est.runs:
        pose = np.asarray(est.runs[run_index].pose, float)
        body.pose__world = pose2_to_pose3(pose) if est.dim == 2 else pose.copy()
        if time is not None:
            t = np.asarray(time, float).reshape(-1)
            if len(t) != len(pose):
                raise TacestError(f"{src}: /runs/{run_index}/pose has {len(pose)} samples, the run file's /time "
                                  f"has {len(t)}: not the run this estimate came from")
            body.time = t
        notes.append(f"Trajectory: /runs/{run_index}/pose ({len(pose)} samples, centre of mass in the recording's "
                     f"world frame{', z up' if est.dim == 3 else ''}"
                     f"{'' if body.time is not None else '; sample times unknown (no run file found)'}).")
    body.params = {
        "mass": body.mass, "inertia": body.inertia__body.tolist(), "friction_ground": body.friction_ground,
        "friction_finger": body.friction_finger, "restitution": body.restitution, "edge_radius": body.edge_radius,
        "ground_offset": body.ground_offset, "linear_damping": body.linear_damping,
        "angular_damping": body.angular_damping,
        "identifiable": {k: bool(v) for k, v in (est.identifiable or {}).items()},
        "source": str(src), "dim": int(est.dim), "depth": (None if est.dim == 3 else
                                                           (DEFAULT_DEPTH if depth is None else float(depth))),
    }
    return body

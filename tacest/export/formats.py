"""Writers of an ExportBody (tacest.export.model): MJCF, URDF, SDF, meshes, a pose CSV.

Every model file starts with a comment block: the body's provenance notes (what came
from which estimate field, what the data could not determine and is a prior), then
what this format expresses and what it cannot.  Mesh-only formats (OBJ, STL, GLB) hold
geometry only; the physical parameters and the notes go to a JSON file beside them
(``NAME.physics.json``), and OBJ and GLB carry the notes too (comment lines, glTF
``extras``).

MJCF (MuJoCo).  A standalone model: a ground plane (at ``ground_offset``), the object
as a body with a free joint, an explicit ``<inertial>`` (mass, ``fullinertia`` about the
centre of mass, body axes), and a convex mesh geom inlined in the file.  Friction is set
with geom priorities so that it holds in the user's own scene too: the object's geom has
``friction_ground`` and priority 1 (a contact with a geom of lower priority, such as
any ground, uses it); the default class ``tacest_finger`` has ``friction_finger`` and
priority 2: give fingertip geoms that class and their contacts with the object use the
finger friction.  Restitution becomes the object's ``solref`` damping ratio (the same
mapping as tacest's 3-D simulator, tacest.sim3d.world.restitution_dampratio); rounded
edges become the geom's ``margin`` on the inner box (a convex shape inflated by a margin
r meets a plane exactly where the shape swept by a ball of radius r does).  The
estimated trajectory is the ``<keyframe>`` (at most ``max_keys`` keys, evenly
subsampled), and ``<custom>`` numerics hold the numbers for scripts.

URDF: one link with ``<inertial>``, ``<visual>`` and ``<collision>`` meshes (an STL
written beside the file and referenced by its relative name), PyBullet's ``<contact>``
(lateral_friction, restitution) in the link and Gazebo's ``<gazebo>`` friction tags.
SDF (1.9): a model with one link, the same mesh, ``<surface>`` friction and bounce.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from tacest.errors import TacestError
from tacest.export.model import MAX_KEYFRAMES, ExportBody
from tacest.io.outputs import atomic_file

log = logging.getLogger(__name__)

FORMATS = ("mjcf", "urdf", "sdf", "obj", "stl", "glb")
#: file suffixes that imply a format when --format is not given
SUFFIX_FORMAT = {".xml": "mjcf", ".mjcf": "mjcf", ".urdf": "urdf", ".sdf": "sdf", ".obj": "obj", ".stl": "stl",
                 ".glb": "glb"}

#: s, MuJoCo timestep of the exported model: tacest's 3-D simulator's substep (0.5 ms at
#: 100 Hz, tacest.sim3d); stiff contacts (CONTACT_TIMECONST) need it
MJ_TIMESTEP = 5e-4
#: rgba of the object in the viewers
RGBA = "0.8 0.45 0.2 1"


def _num(v) -> str:
    return repr(float(v))


def _nums(values) -> str:
    return " ".join(_num(v) for v in np.asarray(values, float).ravel())


def _xml_comment(lines) -> str:
    """An XML comment of the lines ("--" is not allowed inside one)."""
    body = "\n".join("  " + str(s).replace("--", "- -") for s in lines)
    return "<!--\n" + body + "\n-->"


def _expressed(body: ExportBody, fmt: str) -> list:
    """Lines saying which of the body's effects ``fmt`` expresses and which it cannot."""
    out, lost = [], []
    if body.restitution is not None:
        (out if fmt in ("mjcf", "urdf", "sdf") else lost).append(f"restitution {body.restitution:.6g}")
    if body.edge_radius > 0:
        (out if fmt == "mjcf" else lost).append(f"edge_radius {body.edge_radius:.6g} m"
                                                 + (" (as the geom margin on the inner box)" if fmt == "mjcf" else
                                                    " (the mesh is the outer, sharp-edged box)"))
    if body.ground_offset != 0:
        (out if fmt == "mjcf" else lost).append(f"ground_offset {body.ground_offset:.6g} m"
                                                 + (" (the ground plane's height)" if fmt == "mjcf" else ""))
    if body.linear_damping is not None:
        (out if fmt == "sdf" else lost).append(f"linear_drag {body.linear_damping:.6g} N s/m")
    if body.angular_damping is not None:
        (out if fmt == "sdf" else lost).append(f"angular_damping {body.angular_damping:.6g} N m s")
    lines = []
    if out:
        lines.append("Expressed in this file: " + "; ".join(out) + ".")
    if lost:
        lines.append("NOT expressible in this format, left out: " + "; ".join(lost) + ".")
    return lines


# ---------------------------------------------------------------------------------
# MJCF


def subsample_indices(n: int, max_keys) -> np.ndarray:
    """Indices of at most ``max_keys`` samples out of n, evenly spread, first and last
    included (all of them when max_keys is None or >= n)."""
    if n == 0 or max_keys == 0:
        return np.zeros(0, int)
    if max_keys is None or max_keys >= n:
        return np.arange(n)
    if max_keys <= 1:
        return np.array([0])
    return np.unique(np.round(np.linspace(0, n - 1, int(max_keys))).astype(int))


def mjcf_string(body: ExportBody, max_keys=MAX_KEYFRAMES, notes_extra=()) -> str:
    """The MJCF model of ``body`` (module docstring)."""
    from tacest.sim3d.world import CONTACT_SOLIMP, CONTACT_TIMECONST, GRAVITY, IMPRATIO, RESTITUTION_TIMECONST
    from tacest.sim3d.world import restitution_dampratio

    I = np.asarray(body.inertia__body, float)
    full = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
    V = body.inner_vertices__body()
    mu_g, mu_f = body.friction_ground, body.friction_finger
    if body.restitution is not None and body.restitution > 0:
        solref = f"{RESTITUTION_TIMECONST!r} {restitution_dampratio(body.restitution)!r}"
    else:
        solref = f"{CONTACT_TIMECONST!r} 1"
    solimp = _nums(CONTACT_SOLIMP)
    margin = f' margin="{_num(body.edge_radius)}"' if body.edge_radius > 0 else ""
    idx = subsample_indices(len(body.pose__world), max_keys)
    notes = list(body.notes) + _expressed(body, "mjcf") + [
        "Contacts: the object geom has friction_ground and priority 1, so its contact with any geom of lower "
        "priority (a ground) uses friction_ground; give your fingertip geoms class=\"tacest_finger\" "
        "(friction_finger, priority 2) and their contacts with the object use friction_finger.",
        "Options (timestep, elliptic cones, impratio, solref/solimp) are those of tacest's 3-D simulator; "
        "the keyframes are the estimated trajectory" + (f" ({len(idx)} of {len(body.pose__world)} samples)"
                                                        if len(body.pose__world)
                                                        else " (none: the estimate has no run)") + ".",
        *notes_extra,
    ]
    keys = []
    for i in idx:
        t = f' time="{_num(body.time[i])}"' if body.time is not None else ""
        keys.append(f'    <key name="s{int(i)}"{t} qpos="{_nums(body.pose__world[i])}"/>')
    keyframe = ("  <keyframe>\n" + "\n".join(keys) + "\n  </keyframe>\n") if keys else ""
    custom = "".join(f'    <numeric name="tacest_{k}" data="{_num(v)}"/>\n'
                     for k, v in (("mass", body.mass), ("friction_ground", mu_g), ("friction_finger", mu_f),
                                  ("restitution", body.restitution), ("edge_radius", body.edge_radius),
                                  ("ground_offset", body.ground_offset)) if v is not None)
    return f"""<mujoco model={quoteattr(body.name)}>
{_xml_comment(notes)}
  <compiler angle="radian" inertiafromgeom="false"/>
  <option timestep="{MJ_TIMESTEP!r}" gravity="0 0 {-GRAVITY!r}" cone="elliptic" impratio="{IMPRATIO}"
          integrator="implicitfast" solver="Newton" iterations="100" tolerance="1e-10">
    <flag multiccd="enable"/>
  </option>
  <default>
    <default class="tacest_finger">
      <geom friction="{_num(mu_f)} 0 0" condim="3" priority="2" solref="{solref}" solimp="{solimp}"/>
    </default>
  </default>
  <custom>
{custom}  </custom>
  <asset>
    <mesh name="object" vertex="{_nums(V)}" face="{" ".join(str(int(i)) for i in np.asarray(body.faces).ravel())}"/>
  </asset>
  <worldbody>
    <light pos="0 0 2" dir="0 0 -1"/>
    <geom name="ground" type="plane" size="0 0 0.05" pos="0 0 {_num(body.ground_offset)}" friction="{_num(mu_g)} 0 0"
          condim="3"/>
    <body name="object" pos="{_nums(body.pose__world[0, :3]) if len(body.pose__world) else '0 0 0'}"
          quat="{_nums(body.pose__world[0, 3:]) if len(body.pose__world) else '1 0 0 0'}">
      <freejoint name="object"/>
      <inertial pos="0 0 0" mass="{_num(body.mass)}" fullinertia="{_nums(full)}"/>
      <geom name="object" type="mesh" mesh="object" rgba="{RGBA}" friction="{_num(mu_g)} 0 0" condim="3"
            priority="1" solref="{solref}" solimp="{solimp}"{margin}/>
    </body>
  </worldbody>
{keyframe}</mujoco>
"""


# ---------------------------------------------------------------------------------
# URDF and SDF


def _mesh_file(path: Path) -> Path:
    return path.with_suffix(".stl")


def urdf_string(body: ExportBody, mesh_name: str) -> str:
    """The URDF of ``body`` referencing the STL ``mesh_name`` (relative to the URDF)."""
    I = np.asarray(body.inertia__body, float)
    notes = list(body.notes) + _expressed(body, "urdf") + [
        f"Mesh: {mesh_name} beside this file (body frame, m). Friction and restitution: PyBullet's <contact> "
        "in the link and Gazebo's <gazebo> tags (URDF itself has no contact properties); friction_finger has "
        "no URDF tag (a contact property of the pair): see the notes above.",
        "The estimated trajectory is not part of a URDF: export it with --trajectory CSV.",
    ]
    rest = (f'\n      <restitution value="{_num(body.restitution)}"/>' if body.restitution is not None else "")
    geom = f'<geometry><mesh filename={quoteattr(mesh_name)} scale="1 1 1"/></geometry>'
    return f"""<?xml version="1.0"?>
{_xml_comment(notes)}
<robot name={quoteattr(body.name)}>
  <link name="object">
    <inertial>
      <origin xyz="0 0 0" rpy="0 0 0"/>
      <mass value="{_num(body.mass)}"/>
      <inertia ixx="{_num(I[0, 0])}" ixy="{_num(I[0, 1])}" ixz="{_num(I[0, 2])}" iyy="{_num(I[1, 1])}" iyz="{_num(I[1, 2])}" izz="{_num(I[2, 2])}"/>
    </inertial>
    <visual>
      <origin xyz="0 0 0" rpy="0 0 0"/>
      {geom}
    </visual>
    <collision>
      <origin xyz="0 0 0" rpy="0 0 0"/>
      {geom}
    </collision>
    <contact>
      <lateral_friction value="{_num(body.friction_ground)}"/>{rest}
    </contact>
  </link>
  <gazebo reference="object">
    <mu1>{_num(body.friction_ground)}</mu1>
    <mu2>{_num(body.friction_ground)}</mu2>
  </gazebo>
</robot>
"""


def sdf_string(body: ExportBody, mesh_name: str) -> str:
    """The SDF (1.9) of ``body`` referencing the STL ``mesh_name`` (relative)."""
    I = np.asarray(body.inertia__body, float)
    notes = list(body.notes) + _expressed(body, "sdf") + [
        f"Mesh: {mesh_name} beside this file (body frame, m). friction_finger has no SDF tag of its own "
        "(a property of the contact pair): see the notes above.",
        "The pose is the trajectory's first sample; the trajectory itself: export it with --trajectory CSV.",
    ]
    pose = body.pose__world[0] if len(body.pose__world) else np.array([0, 0, 0, 1, 0, 0, 0.0])
    rpy = _rpy(pose[3:])
    bounce = (f"\n          <bounce><restitution_coefficient>{_num(body.restitution)}</restitution_coefficient>"
              "<threshold>0</threshold></bounce>" if body.restitution is not None else "")
    decay = ""
    if body.linear_damping is not None or body.angular_damping is not None:
        # SDF's velocity_decay is a rate (1/s): damping (N s/m, N m s) over mass (or inertia)
        lin = 0.0 if body.linear_damping is None else body.linear_damping / body.mass
        ang = 0.0 if body.angular_damping is None else body.angular_damping / float(np.mean(np.diag(I)))
        decay = f"\n      <velocity_decay><linear>{_num(lin)}</linear><angular>{_num(ang)}</angular></velocity_decay>"
    geom = f"<geometry><mesh><uri>{mesh_name}</uri></mesh></geometry>"
    return f"""<?xml version="1.0"?>
{_xml_comment(notes)}
<sdf version="1.9">
  <model name={quoteattr(body.name)}>
    <pose>{_nums(pose[:3])} {_nums(rpy)}</pose>
    <link name="object">
      <inertial>
        <pose>0 0 0 0 0 0</pose>
        <mass>{_num(body.mass)}</mass>
        <inertia>
          <ixx>{_num(I[0, 0])}</ixx><ixy>{_num(I[0, 1])}</ixy><ixz>{_num(I[0, 2])}</ixz>
          <iyy>{_num(I[1, 1])}</iyy><iyz>{_num(I[1, 2])}</iyz><izz>{_num(I[2, 2])}</izz>
        </inertia>
      </inertial>{decay}
      <collision name="collision">
        {geom}
        <surface>
          <friction><ode><mu>{_num(body.friction_ground)}</mu><mu2>{_num(body.friction_ground)}</mu2></ode></friction>{bounce}
        </surface>
      </collision>
      <visual name="visual">
        {geom}
      </visual>
    </link>
  </model>
</sdf>
"""


def _rpy(q) -> np.ndarray:
    """(3,) roll, pitch, yaw (rad, fixed axes x, y, z) of a quaternion [qw, qx, qy, qz]."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = np.asarray(q, float)
    return Rotation.from_quat([x, y, z, w]).as_euler("xyz")


# ---------------------------------------------------------------------------------
# files


def physics_json(body: ExportBody) -> str:
    """The body's numbers and notes as JSON (the sidecar of the mesh formats)."""
    return json.dumps({"format": "tacest.export", "version": 1, "frame": "body frame, origin at the centre of mass, m",
                       **body.params, "notes": list(body.notes)}, indent=2)


def write_trajectory_csv(body: ExportBody, path) -> None:
    """The pose trajectory as CSV: ``sample, time, x, y, z, qw, qx, qy, qz`` (m, s;
    time empty when unknown), one row per sample; written atomically."""
    with atomic_file(path) as tmp, tmp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["sample", "time", "x", "y", "z", "qw", "qx", "qy", "qz"])
        for k, pose in enumerate(body.pose__world):
            t = "" if body.time is None else repr(float(body.time[k]))
            w.writerow([k, t, *(repr(float(v)) for v in pose)])


def export_paths(path, fmt: str) -> list:
    """The files :func:`write_export` writes for ``path`` in ``fmt``: the model file, and
    the STL mesh of URDF/SDF or the ``NAME.physics.json`` of the mesh formats beside it
    (the command checks them all before any work)."""
    path = Path(path)
    if fmt not in FORMATS:
        raise TacestError(f"--format {fmt}: expected one of {', '.join(FORMATS)}")
    if fmt == "mjcf":
        return [path]
    if fmt in ("urdf", "sdf"):
        mesh_path = _mesh_file(path)
        if mesh_path == path:
            raise TacestError(f"{path}: a {fmt.upper()} file needs another suffix than .stl (its mesh is written as .stl)")
        return [path, mesh_path]
    return [path, path.with_name(path.stem + ".physics.json")]


def write_export(body: ExportBody, path, fmt: str, max_keys=MAX_KEYFRAMES) -> list:
    """Write ``body`` to ``path`` in ``fmt`` (FORMATS); returns the files written
    (:func:`export_paths`), each written atomically (tacest.io.outputs.atomic_file)."""
    written = export_paths(path, fmt)
    path = written[0]
    if fmt == "mjcf":
        with atomic_file(path) as tmp:
            tmp.write_text(mjcf_string(body, max_keys=max_keys))
    elif fmt in ("urdf", "sdf"):
        mesh_path = written[1]
        with atomic_file(mesh_path) as tmp:
            body.mesh().export(str(tmp), file_type="stl")
        text = urdf_string(body, mesh_path.name) if fmt == "urdf" else sdf_string(body, mesh_path.name)
        with atomic_file(path) as tmp:
            tmp.write_text(text)
    else:
        _write_mesh_format(body, path, fmt)
        with atomic_file(written[1]) as tmp:
            tmp.write_text(physics_json(body))
    log.info("wrote %s", ", ".join(str(p) for p in written))
    return written


def _write_mesh_format(body: ExportBody, path: Path, fmt: str) -> None:
    """The geometry alone as OBJ, GLB or STL at ``path`` (the numbers go to the
    ``NAME.physics.json`` beside it)."""
    mesh = body.mesh()
    notes = list(body.notes) + _expressed(body, fmt) + [
        f"This file holds the geometry only (body frame, m); the physical parameters are in "
        f"{path.stem}.physics.json beside it."]
    with atomic_file(path) as tmp:
        if fmt == "obj":
            text = mesh.export(file_type="obj", include_normals=False)
            header = "".join(f"# {line}\n" for line in notes)
            tmp.write_text(header + text)
        elif fmt == "glb":
            import trimesh

            scene = trimesh.Scene(mesh)
            scene.metadata["tacest"] = {**body.params, "notes": notes}
            tmp.write_bytes(trimesh.exchange.gltf.export_glb(scene))  # metadata: /scenes/0/extras
        else:
            mesh.export(str(tmp), file_type="stl")


def check_finite_body(body: ExportBody, source: str) -> None:
    """A TacestError naming ``source`` when a number to export is not finite or the
    inertia is not a physical one (MuJoCo and URDF tools would reject it)."""
    I = np.asarray(body.inertia__body, float)
    if not (math.isfinite(body.mass) and body.mass > 0):
        raise TacestError(f"{source}: /params attrs mass: {body.mass} is not a positive mass")
    if not np.all(np.isfinite(I)) or np.min(np.linalg.eigvalsh(0.5 * (I + I.T))) <= 0:
        raise TacestError(f"{source}: /params attrs inertia: not a positive definite inertia")
    for k in ("friction_ground", "friction_finger"):
        v = getattr(body, k)
        if not (math.isfinite(v) and v >= 0):
            raise TacestError(f"{source}: /params attrs {k}: {v} is not a friction coefficient")

"""Dome calibration of a vision-based tactile fingertip (DenseTact-like) and JSON I/O.

The fingertip is a hemispherical elastomer dome watched from inside by a camera on its
axis.  The calibration is an image-plane model of the dome, not full camera intrinsics:

- ``center_px`` (u, v): pixel where the dome's axis (its apex) appears;
- ``rim_radius_px``: radius, in px, of the circle where the dome's rim appears;
- ``rim_polar_angle_deg``: polar angle of that rim seen from the dome centre (90 for a
  hemisphere);
- ``projection``: how the polar angle theta of a point of the dome maps to its image
  distance rho = |(u, v) - center| / rim_radius_px (rho = 1 on the rim):
  ``equidistant`` (fisheye, theta = rho * theta_rim; the default: a wide-angle camera
  at the dome centre, uniform angular resolution up to the rim) or ``orthographic``
  (sin theta = rho * sin theta_rim: a telecentric view from far below);
- ``dome_radius_m``, ``finger_radius_m`` (m): the dome's radius, and the fingertip
  radius written to the run (default: the dome radius);
- ``rotation_world_from_finger``: 3x3 rotation taking finger-frame vectors to the world
  frame (optional when the finger log has per-sample quaternions).

Finger frame = camera frame in OpenCV convention: x along image u (right), y along
image v (down), z along the dome axis out through the apex (the camera's viewing
direction).  It is right-handed (x cross y = z).  A point of the dome at polar angle
theta and azimuth az = atan2(v - v_c, u - u_c) has the fingertip's outward unit normal

    n_finger = (sin theta cos az, sin theta sin az, cos theta)      (finger frame)

and SPEC's ``/tactile/normal`` -- the object's outward normal, pointing from the object
into the finger -- is its opposite rotated to the world: ``n_obj = -R_wf n_finger``.
In a 2-D run the world plane is the (x, y) plane of the 3-D world frame: the normal is
projected onto it and renormalised.

The JSON file (``docs/tactile_video.md`` has an example)::

    {"format": "tacest.dome_calibration", "version": 1,
     "image_size": [640, 480], "center_px": [320, 240], "rim_radius_px": 220,
     "rim_polar_angle_deg": 90, "projection": "equidistant",
     "dome_radius_m": 0.012, "finger_radius_m": 0.012,
     "rotation_world_from_finger": [[1,0,0],[0,-1,0],[0,0,-1]]}

Unknown keys are an error (a typo must not silently fall back to a default), except
keys starting with ``_`` or named ``comment``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from tacest.errors import TacestError

FORMAT = "tacest.dome_calibration"
VERSION = 1
PROJECTIONS = ("equidistant", "orthographic")

#: Tolerance on R^T R - I and det R - 1 for a hand-written rotation: 4 decimals per entry
#: (e.g. 0.7071) leave an error of ~1e-4; 1e-3 still rejects anything that is not a
#: rotation.  Accepted matrices are re-orthonormalised (SVD) before use.
ROTATION_TOL = 1e-3

_REQUIRED = ("image_size", "center_px", "rim_radius_px", "dome_radius_m")
_OPTIONAL = ("format", "version", "rim_polar_angle_deg", "projection", "finger_radius_m",
             "rotation_world_from_finger", "comment")


@dataclass
class DomeCalibration:
    """Image-plane model of a tactile dome (see the module docstring).

    image_size : (2,) int, (width, height) px
    center_px : (2,) float, (u, v) px of the dome apex
    rim_radius_px : float, px
    dome_radius_m : float, m
    rim_polar_angle_deg : float, deg, in (0, 180)
    projection : "equidistant" | "orthographic"
    finger_radius_m : float, m (None: the dome radius)
    rotation_world_from_finger : (3, 3) float or None
    """

    image_size: tuple
    center_px: np.ndarray
    rim_radius_px: float
    dome_radius_m: float
    rim_polar_angle_deg: float = 90.0
    projection: str = "equidistant"
    finger_radius_m: Optional[float] = None
    rotation_world_from_finger: Optional[np.ndarray] = None
    extra: dict = field(default_factory=dict)

    @property
    def finger_radius(self) -> float:
        """Fingertip radius for the run, m."""
        return float(self.finger_radius_m if self.finger_radius_m is not None else self.dome_radius_m)

    @property
    def theta_rim(self) -> float:
        """Polar angle of the rim, rad."""
        return float(np.deg2rad(self.rim_polar_angle_deg))

    # -- image <-> dome ------------------------------------------------------------
    def polar_of_rho(self, rho):
        """Polar angle theta (rad) of normalised image radius ``rho`` (1 on the rim)."""
        rho = np.asarray(rho, float)
        if self.projection == "equidistant":
            return rho * self.theta_rim
        return np.arcsin(np.clip(rho * np.sin(self.theta_rim), -1.0, 1.0))

    def rho_of_polar(self, theta):
        """Normalised image radius of polar angle ``theta`` (rad); inverse of polar_of_rho."""
        theta = np.asarray(theta, float)
        if self.projection == "equidistant":
            return theta / self.theta_rim
        return np.sin(theta) / np.sin(self.theta_rim)

    def finger_normal(self, uv) -> np.ndarray:
        """Fingertip outward unit normal, finger frame, at image points ``uv`` (..., 2) px
        -> (..., 3).  Points beyond the rim are clamped to the rim."""
        uv = np.asarray(uv, float)
        d = uv - np.asarray(self.center_px, float)
        rho = np.minimum(np.hypot(d[..., 0], d[..., 1]) / self.rim_radius_px, 1.0)
        theta = self.polar_of_rho(rho)
        az = np.arctan2(d[..., 1], d[..., 0])
        s = np.sin(theta)
        return np.stack([s * np.cos(az), s * np.sin(az), np.cos(theta)], axis=-1)

    def pixel_of_finger_direction(self, n_finger) -> np.ndarray:
        """Image point (..., 2) px where the dome point with outward normal ``n_finger``
        (..., 3), finger frame, appears.  Inverse of :meth:`finger_normal`."""
        n = np.asarray(n_finger, float)
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        theta = np.arccos(np.clip(n[..., 2], -1.0, 1.0))
        az = np.arctan2(n[..., 1], n[..., 0])
        r = self.rho_of_polar(theta) * self.rim_radius_px
        return np.asarray(self.center_px, float) + np.stack([r * np.cos(az), r * np.sin(az)], axis=-1)

    def object_normal(self, uv, rotation_world_from_finger=None, dim: int = 3):
        """SPEC ``/tactile/normal`` for a contact seen at image point(s) ``uv`` (..., 2) px.

        n_obj = -R_wf n_finger(uv): the object's outward normal points from the object into
        the finger, i.e. against the fingertip's own outward normal at the contact.

        rotation_world_from_finger : (3, 3) or (..., 3, 3); default: the calibration's.
        dim : 3, or 2 to project onto the world (x, y) plane and renormalise.
        Returns (normal (..., dim), inplane_norm (...)): ``inplane_norm`` is the length of
        the projected normal before renormalising (1 in 3-D); a tiny value means the
        contact normal is nearly perpendicular to the 2-D world plane.
        """
        R = self.rotation_world_from_finger if rotation_world_from_finger is None else rotation_world_from_finger
        if R is None:
            raise TacestError("the calibration has no rotation_world_from_finger and no orientation was given")
        nf = self.finger_normal(uv)
        n_world = -np.einsum("...ij,...j->...i", np.asarray(R, float), nf)
        if dim == 3:
            return n_world, np.ones(n_world.shape[:-1])
        p = n_world[..., :2]
        norm = np.linalg.norm(p, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return p / norm[..., None], norm

    # -- JSON -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = {"format": FORMAT, "version": VERSION,
             "image_size": [int(self.image_size[0]), int(self.image_size[1])],
             "center_px": [float(c) for c in self.center_px],
             "rim_radius_px": float(self.rim_radius_px),
             "rim_polar_angle_deg": float(self.rim_polar_angle_deg),
             "projection": self.projection,
             "dome_radius_m": float(self.dome_radius_m),
             "finger_radius_m": self.finger_radius}
        if self.rotation_world_from_finger is not None:
            d["rotation_world_from_finger"] = np.asarray(self.rotation_world_from_finger, float).round(12).tolist()
        return d

    def to_json(self) -> str:
        """JSON text, one key per line (lists kept on their key's line)."""
        items = [f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in self.to_dict().items()]
        return "{\n" + ",\n".join(items) + "\n}"

    def save(self, path) -> None:
        Path(path).write_text(self.to_json() + "\n")


def load_calibration(path) -> DomeCalibration:
    """Read and validate a dome calibration JSON file; TacestError (one line) if bad."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise TacestError(f"{path}: cannot read calibration ({exc.strerror or exc})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise TacestError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    return calibration_from_dict(data, source=str(path))


def calibration_from_dict(data, source: str = "<calibration>") -> DomeCalibration:
    """Validate a parsed calibration (see the module docstring); TacestError if bad."""

    def fail(key, problem):
        raise TacestError(f"{source}: {key}: {problem}")

    if not isinstance(data, dict):
        raise TacestError(f"{source}: expected a JSON object at the top level")
    for key in _REQUIRED:
        if key not in data:
            raise TacestError(f"{source}: missing key {key!r} (required: {', '.join(_REQUIRED)})")
    unknown = [k for k in data if k not in _REQUIRED + _OPTIONAL and not k.startswith("_")]
    if unknown:
        fail(unknown[0], "unknown key (see docs/tactile_video.md for the calibration keys)")
    if "format" in data and data["format"] != FORMAT:
        fail("format", f"expected {FORMAT!r}, got {data['format']!r}")
    if "version" in data and data["version"] != VERSION:
        fail("version", f"unknown version {data['version']!r} (this tacest reads {VERSION})")

    def vector(key, n):
        try:
            v = np.asarray(data[key], float)
        except (TypeError, ValueError):
            fail(key, f"expected {n} numbers")
        if v.shape != (n,) or not np.all(np.isfinite(v)):
            fail(key, f"expected {n} finite numbers, got {data[key]!r}")
        return v

    def positive(key, default=None):
        if key not in data or data[key] is None:
            return default
        try:
            v = float(data[key])
        except (TypeError, ValueError):
            fail(key, f"expected a number, got {data[key]!r}")
        if not (np.isfinite(v) and v > 0):
            fail(key, f"must be > 0, got {data[key]!r}")
        return v

    size = vector("image_size", 2)
    if np.any(size < 1) or np.any(size != np.round(size)):
        fail("image_size", f"expected [width, height] in px, got {data['image_size']!r}")
    center = vector("center_px", 2)
    rim = positive("rim_radius_px")
    dome_r = positive("dome_radius_m")
    finger_r = positive("finger_radius_m")
    rim_deg = positive("rim_polar_angle_deg", 90.0)
    if rim_deg >= 180.0:
        fail("rim_polar_angle_deg", f"must be in (0, 180), got {rim_deg}")
    projection = data.get("projection", "equidistant")
    if projection not in PROJECTIONS:
        fail("projection", f"expected one of {', '.join(PROJECTIONS)}, got {projection!r}")
    if projection == "orthographic" and rim_deg > 90.0:
        fail("rim_polar_angle_deg", "an orthographic view cannot see beyond 90 degrees")
    R = None
    if data.get("rotation_world_from_finger") is not None:
        R = check_rotation(data["rotation_world_from_finger"], f"{source}: rotation_world_from_finger")
    extra = {k: v for k, v in data.items() if k.startswith("_") or k == "comment"}
    return DomeCalibration(image_size=(int(size[0]), int(size[1])), center_px=center, rim_radius_px=rim,
                           dome_radius_m=dome_r, rim_polar_angle_deg=rim_deg, projection=projection,
                           finger_radius_m=finger_r, rotation_world_from_finger=R, extra=extra)


def check_rotation(value, where: str) -> np.ndarray:
    """Validate a 3x3 rotation matrix (within ROTATION_TOL) and return it re-orthonormalised."""
    try:
        R = np.asarray(value, float)
    except (TypeError, ValueError):
        raise TacestError(f"{where}: expected a 3x3 matrix of numbers") from None
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise TacestError(f"{where}: expected a 3x3 matrix of finite numbers, got shape {R.shape}")
    if np.max(np.abs(R.T @ R - np.eye(3))) > ROTATION_TOL or abs(np.linalg.det(R) - 1.0) > ROTATION_TOL:
        raise TacestError(f"{where}: not a rotation matrix (needs R^T R = I and det R = +1)")
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt

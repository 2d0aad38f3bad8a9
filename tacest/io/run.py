"""Run files (``tacest.run``, SPEC v1): one recorded trajectory.

Every stage reads and writes run files through this module.  :func:`read_run`
validates the whole file on open and raises :class:`FileFormatError` naming the file
and the offending HDF5 path; :func:`write_run` writes atomically (temporary name,
renamed into place when complete).

Array conventions (T samples, F fingers, D = dim, P = pose size = 3 or 7)::

    time             (T,)      s, strictly increasing, uniform spacing dt
    finger_position  (T, F, D) m, world frame, fingertip centre
    finger_radius    (F,)      m
    contact          (T, F)    uint8 in {0, 1}
    force            (T, F, D) N, mean force finger f exerts ON the object, world frame
    normal           (T, F, D) unit outward object normal at the contact, NaN where c = 0
    pose_obs         (T, P)    observed pose, NaN rows where missing
    missing          (T,)      uint8, optional (``/quality/missing``, a tacest extension
                               documented in docs/formats.md): 1 where the sample never
                               arrived (serial gap); robot/tactile values there are
                               placeholders (position interpolated, contact 0, force 0,
                               normal NaN) and estimators give them no weight
    missing_finger   (T, F)    uint8, optional (``/quality/missing_finger``, tacest
                               extension): 1 where finger f's robot and tactile values of
                               sample k are unknown (one finger's serial line lost while
                               its siblings arrived); when present, ``missing`` must be
                               its OR over fingers.  :attr:`Run.finger_missing_mask` gives
                               the (T, F) mask whichever of the two a file has
"""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from tacest.errors import FileFormatError
from tacest.geometry.transforms import pose_size
from tacest.io.h5util import Reader, atomic_h5, attr_str, open_h5, sha256_file
from tacest.provenance import PROVENANCE_ATTRS, provenance, sha256_text

FORMAT = "tacest.run"
VERSION = 1

#: Tolerance on |n| - 1 for stored unit normals and quaternions.  Files store float64
#: (or float32: 1e-7 relative); sensors that normalise in float32 and then round to a
#: few decimals in a text protocol stay within 1e-3.
UNIT_NORM_TOL = 1e-3

#: Plausibility limits.  A value beyond one is not a measurement of a hand-sized object
#: poked on a table but a unit or encoding error (millimetres written as metres, a
#: sensor's overflow value, an uninitialised buffer), and the reader names it instead of
#: handing it to the estimator (docs/formats.md, "Validation"):
#: N, |force component|: 10 kN is a tonne-force, two orders above the range of any
#: fingertip or wrist force sensor (tactile skins ~10 N, wrist F/T sensors up to ~1 kN)
MAX_ABS_FORCE = 1e4
#: m, |position coordinate| (fingertips, observed poses, ground height): a 100 m
#: world exceeds any robot cell or motion-capture volume (~10 m); 10 mm written as
#: millimetres reads as 10 m, 150 mm as 150 m
MAX_ABS_POSITION = 100.0
#: m, finger radius: a fingertip is millimetres to centimetres
MAX_FINGER_RADIUS = 1.0
#: s, sample period: 1 MHz to 1 Hz (tactile and motion-capture streams run at 30 Hz to
#: a few kHz; below 1 Hz there is no contact dynamics left to see)
MIN_DT, MAX_DT = 1e-6, 1.0
#: m/s², |gravity|: 10 g (a value in mm/s² or ft/s² in g units reads far above)
MAX_GRAVITY = 100.0

#: Defaults for /observations/pose noise levels when a writer left the attrs out
#: (documented in docs/formats.md; a note is printed when they are used).
DEFAULT_SIGMA_POSITION = 1e-3  # m
DEFAULT_SIGMA_ANGLE = 1e-2  # rad


def velocity_size(dim: int) -> int:
    """Length of a velocity vector: 3 in 2-D ([vx, vy, omega]), 6 in 3-D ([v (3), omega (3)])."""
    return 3 if dim == 2 else 6


@dataclass
class Truth:
    """Ground truth of a simulated run (``/truth``).

    pose : (T, P) float; vertices : (K, D) float, m, body frame (origin at the COM);
    inertia : float (2-D, kg·m²) or (3, 3) (3-D), about the COM;
    effects : list of dicts ``{"name": ..., param: value, ...}``.
    """

    pose: np.ndarray
    vertices: np.ndarray
    mass: float
    inertia: object
    friction_ground: float
    friction_finger: float
    effects: list = field(default_factory=list)


@dataclass
class Actions:
    """Actions (pokes): ``segments`` (A, 2) int [start, stop) sample indices,
    ``params`` (A, n) float, ``kind`` str, ``names`` list of n str."""

    segments: np.ndarray
    params: np.ndarray
    kind: str = "poke"
    names: list = field(default_factory=list)


@dataclass
class Run:
    """One recorded trajectory, as in SPEC.  See the module docstring for shapes."""

    dim: int
    dt: float
    time: np.ndarray
    gravity: np.ndarray
    source: str = "unknown"
    finger_position: Optional[np.ndarray] = None
    finger_radius: Optional[np.ndarray] = None
    contact: Optional[np.ndarray] = None
    force: Optional[np.ndarray] = None
    normal: Optional[np.ndarray] = None
    pose_obs: Optional[np.ndarray] = None
    sigma_position: float = DEFAULT_SIGMA_POSITION
    sigma_angle: float = DEFAULT_SIGMA_ANGLE
    actions: Optional[Actions] = None
    ground_height: float = 0.0
    ground_normal: Optional[np.ndarray] = None
    prior: dict = field(default_factory=dict)
    truth: Optional[Truth] = None
    missing: Optional[np.ndarray] = None
    missing_finger: Optional[np.ndarray] = None
    #: extra root attributes to keep (str -> JSON-able), e.g. recorder settings
    extra_attrs: dict = field(default_factory=dict)
    #: where it was read from (not written)
    filename: Optional[str] = None
    #: SHA-256 (hex) of the file it was read from, taken when it was read (not written):
    #: an estimate names its source by it even where the file is not at hand (a Dask
    #: worker on another machine, docs/parallel.md)
    sha256: Optional[str] = None

    # -- derived sizes -------------------------------------------------------------
    @property
    def n_samples(self) -> int:
        return int(self.time.shape[0])

    @property
    def n_fingers(self) -> int:
        return 0 if self.finger_position is None else int(self.finger_position.shape[1])

    @property
    def has_tactile(self) -> bool:
        return self.contact is not None

    @property
    def has_force(self) -> bool:
        return self.force is not None

    @property
    def has_pose_obs(self) -> bool:
        return self.pose_obs is not None

    @property
    def finger_missing_mask(self) -> np.ndarray:
        """(T, F) bool: True where finger f's position, contact, force and normal at
        sample k are unknown placeholders.  From ``/quality/missing_finger`` when the run
        has it, else ``/quality/missing`` repeated over the fingers, else all False."""
        T, F = self.n_samples, self.n_fingers
        if self.missing_finger is not None:
            return np.asarray(self.missing_finger).astype(bool).reshape(T, F)
        if self.missing is not None:
            return np.repeat(np.asarray(self.missing).astype(bool).reshape(T, 1), F, axis=1)
        return np.zeros((T, F), bool)

    @property
    def up(self) -> np.ndarray:
        """(D,) unit ground normal, world frame."""
        if self.ground_normal is not None:
            return np.asarray(self.ground_normal, float)
        e = np.zeros(self.dim)
        e[-1] = 1.0
        return e

    def replace(self, **changes) -> "Run":
        return dataclasses.replace(self, **changes)

    def validate(self, filename="<run>"):
        """Check shapes and values against SPEC; raise FileFormatError on the first problem."""
        _validate(self, filename)
        return self


# ---------------------------------------------------------------------------------
# validation (shared by read and write, so nothing invalid is ever written)


def _fail(filename, path, problem):
    raise FileFormatError(filename, path, problem)


def _check_shape(filename, path, arr, shape):
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        _fail(filename, path, f"expected shape {want}, got {arr.shape}")


def _check_finite(filename, path, arr):
    if not np.all(np.isfinite(arr)):
        _fail(filename, path, "contains NaN or inf where values are required")


def check_plausible(filename, path, arr, limit, unit, name):
    """FileFormatError naming the first entry of ``arr`` with |value| > limit (NaN
    passes); ``name`` is the limit's constant in this module."""
    arr = np.asarray(arr, float)
    with np.errstate(invalid="ignore"):
        bad = np.abs(arr) > limit
    if np.any(bad):
        at = tuple(int(i) for i in np.argwhere(bad)[0])
        where = f" at index {list(at)}" if at else ""
        _fail(filename, path, f"{arr[at]:.3g} {unit}{where} is beyond the plausibility limit "
              f"{limit:g} {unit} (tacest.io.run.{name}; a unit or encoding error?)")


def _validate(run: Run, filename):
    """Validate ``run`` against SPEC (:func:`_validate_values`); FileFormatError on the
    first problem."""
    # absurd values (1e300) may overflow in the checks (a norm): they fail the check,
    # and numpy's warning would only be a second line on stderr
    with np.errstate(over="ignore", invalid="ignore"):
        _validate_values(run, filename)


def _validate_values(run: Run, filename):
    """Every check of :meth:`Run.validate`, in this order (the first failing one raises):
    the clock, the fingers and the tactile streams, the pose observations, the quality
    masks, the actions, the scene and prior, the truth."""
    T = _validate_clock(run, filename)
    F = _validate_fingers(run, filename, T)
    if run.pose_obs is not None:
        _validate_pose_obs(run, filename, T)
    _validate_quality(run, filename, T, F)
    if run.actions is not None:
        _validate_actions(run, filename, T)
    _validate_scene_and_prior(run, filename)
    if run.truth is not None:
        _validate_truth(run, filename, T)


def _validate_clock(run: Run, filename) -> int:
    """dim, dt, gravity and /time (strictly increasing, uniform with dt); returns the
    number of samples T."""
    D = run.dim
    if D not in (2, 3):
        _fail(filename, "attrs dim", f"must be 2 or 3, got {D}")
    if not (np.isfinite(run.dt) and run.dt > 0):
        _fail(filename, "attrs dt", f"must be a positive number, got {run.dt}")
    if not MIN_DT <= run.dt <= MAX_DT:
        _fail(filename, "attrs dt", f"{run.dt:.3g} s is outside the plausible sample periods [{MIN_DT:g}, "
              f"{MAX_DT:g}] s (tacest.io.run.MIN_DT, MAX_DT)")
    g = np.asarray(run.gravity, float)
    _check_shape(filename, "attrs gravity", g, (D,))
    _check_finite(filename, "attrs gravity", g)
    if np.linalg.norm(g) > MAX_GRAVITY:
        _fail(filename, "attrs gravity", f"|gravity| = {np.linalg.norm(g):.3g} m/s² is beyond the plausibility "
              f"limit {MAX_GRAVITY:g} m/s² (tacest.io.run.MAX_GRAVITY; a unit error?)")
    t = np.asarray(run.time, float)
    _check_shape(filename, "/time", t, (None,))
    _check_finite(filename, "/time", t)
    T = t.shape[0]
    if T < 2:
        _fail(filename, "/time", f"needs at least 2 samples, got {T}")
    dts = np.diff(t)
    if np.any(dts <= 0):
        k = int(np.argmax(dts <= 0)) + 1
        _fail(filename, "/time", f"must be strictly increasing (sample {k}: {t[k]} after {t[k-1]})")
    # uniform sampling: tolerance relative to dt, generous for float32 clocks
    if np.max(np.abs(dts - run.dt)) > 1e-3 * run.dt + 1e-6 * max(1.0, abs(t[-1])):
        k = int(np.argmax(np.abs(dts - run.dt))) + 1
        _fail(filename, "/time", f"samples are not uniform with dt = {run.dt} "
              f"(step {k} is {dts[k-1]})")
    return T


def _validate_fingers(run: Run, filename, T: int) -> Optional[int]:
    """/robot and /tactile: present together, or neither when the run has pose
    observations; returns the number of fingers F (None without /robot)."""
    has_robot = run.finger_position is not None
    has_tactile = run.contact is not None
    if not has_tactile and run.pose_obs is None:
        _fail(filename, "/tactile", "a run needs /tactile or /observations; found neither")
    if has_tactile and not has_robot:
        _fail(filename, "/robot/finger_position", "required when /tactile is present")
    F = None
    if has_robot:
        F = _validate_robot(run, filename, T)
        if not has_tactile:
            _fail(filename, "/tactile/contact", "required when /robot is present")
    if has_tactile:
        _validate_tactile(run, filename, T, F)
    return F


def _validate_robot(run: Run, filename, T: int) -> int:
    """/robot/finger_position (T, F, D), finite and plausible, and /robot/finger_radius
    (F,), positive and plausible; returns F."""
    D = run.dim
    fp = np.asarray(run.finger_position, float)
    if fp.ndim != 3 or fp.shape[0] != T or fp.shape[2] != D:
        _fail(filename, "/robot/finger_position", f"expected shape ({T}, F, {D}), got {fp.shape}")
    _check_finite(filename, "/robot/finger_position", fp)
    check_plausible(filename, "/robot/finger_position", fp, MAX_ABS_POSITION, "m", "MAX_ABS_POSITION")
    F = fp.shape[1]
    if F < 1:
        _fail(filename, "/robot/finger_position", "needs at least one finger")
    if run.finger_radius is None:
        _fail(filename, "/robot/finger_radius", "required dataset is missing")
    rad = np.asarray(run.finger_radius, float)
    _check_shape(filename, "/robot/finger_radius", rad, (F,))
    _check_finite(filename, "/robot/finger_radius", rad)
    if np.any(rad <= 0):
        _fail(filename, "/robot/finger_radius", "radii must be > 0")
    check_plausible(filename, "/robot/finger_radius", rad, MAX_FINGER_RADIUS, "m", "MAX_FINGER_RADIUS")
    return F


def _validate_tactile(run: Run, filename, T: int, F: int) -> None:
    """/tactile/contact (0 or 1), /tactile/normal (unit where in contact, NaN allowed
    elsewhere, never inf) and the optional /tactile/force (finite, plausible)."""
    D = run.dim
    c = np.asarray(run.contact)
    _check_shape(filename, "/tactile/contact", c, (T, F))
    if not np.all(np.isin(c, (0, 1))):
        _fail(filename, "/tactile/contact", "values must be 0 or 1")
    on = c.astype(bool)
    if run.normal is None:
        _fail(filename, "/tactile/normal", "required dataset is missing")
    n = np.asarray(run.normal, float)
    _check_shape(filename, "/tactile/normal", n, (T, F, D))
    if np.any(np.isinf(n)):
        _fail(filename, "/tactile/normal", "contains inf")
    n_on = n[on]
    if n_on.size:
        if not np.all(np.isfinite(n_on)):
            k = int(np.argwhere(on & ~np.all(np.isfinite(n), axis=-1))[0][0])
            _fail(filename, "/tactile/normal", f"NaN at sample {k} where contact = 1")
        norms = np.linalg.norm(n_on, axis=-1)
        bad = np.abs(norms - 1.0) > UNIT_NORM_TOL
        if np.any(bad):
            _fail(filename, "/tactile/normal",
                  f"not a unit vector where contact = 1 (|n| = {norms[bad][0]:.6g})")
    if run.force is not None:
        fz = np.asarray(run.force, float)
        _check_shape(filename, "/tactile/force", fz, (T, F, D))
        _check_finite(filename, "/tactile/force", fz)
        check_plausible(filename, "/tactile/force", fz, MAX_ABS_FORCE, "N", "MAX_ABS_FORCE")


def _validate_pose_obs(run: Run, filename, T: int) -> None:
    """/observations/pose (T, P): positions plausible, missing rows all NaN, unit
    quaternions in 3-D, positive noise levels."""
    D = run.dim
    P = pose_size(D)
    po = np.asarray(run.pose_obs, float)
    _check_shape(filename, "/observations/pose", po, (T, P))
    if np.any(np.isinf(po)):
        _fail(filename, "/observations/pose", "contains inf")
    check_plausible(filename, "/observations/pose", po[:, :D], MAX_ABS_POSITION, "m", "MAX_ABS_POSITION")
    nanrow = np.isnan(po)
    partial = np.any(nanrow, axis=1) & ~np.all(nanrow, axis=1)
    if np.any(partial):
        _fail(filename, "/observations/pose",
              f"row {int(np.argmax(partial))} is partly NaN (missing rows must be all NaN)")
    if D == 3:
        ok = ~np.any(nanrow, axis=1)
        qn = np.linalg.norm(po[ok, 3:7], axis=1)
        if np.any(np.abs(qn - 1.0) > UNIT_NORM_TOL):
            _fail(filename, "/observations/pose", "quaternions must be unit length")
    for name in ("sigma_position", "sigma_angle"):
        val = getattr(run, name)
        if not (np.isfinite(val) and val > 0):
            _fail(filename, f"/observations/pose attrs {name}", f"must be > 0, got {val}")


def _validate_quality(run: Run, filename, T: int, F: Optional[int]) -> None:
    """/quality/missing (T,) and /quality/missing_finger (T, F), 0 or 1; the first the
    OR over fingers of the second."""
    if run.missing is not None:
        ms = np.asarray(run.missing)
        _check_shape(filename, "/quality/missing", ms, (T,))
        if not np.all(np.isin(ms, (0, 1))):
            _fail(filename, "/quality/missing", "values must be 0 or 1")
    if run.missing_finger is not None:
        if F is None:  # no /robot
            _fail(filename, "/quality/missing_finger", "needs /robot (it is per finger)")
        mf = np.asarray(run.missing_finger)
        _check_shape(filename, "/quality/missing_finger", mf, (T, F))
        if not np.all(np.isin(mf, (0, 1))):
            _fail(filename, "/quality/missing_finger", "values must be 0 or 1")
        if run.missing is None:
            _fail(filename, "/quality/missing", "required when /quality/missing_finger is present "
                  "(1 where any finger of the sample is missing)")
        bad = np.asarray(run.missing).astype(bool) != mf.astype(bool).any(axis=1)
        if np.any(bad):
            _fail(filename, "/quality/missing", f"must be 1 exactly where /quality/missing_finger has a 1 "
                  f"(sample {int(np.argmax(bad))} disagrees)")


def _validate_actions(run: Run, filename, T: int) -> None:
    """/actions/segments ([start, stop) rows within the run) and /actions/params (one
    finite row per segment)."""
    seg = np.asarray(run.actions.segments)
    _check_shape(filename, "/actions/segments", seg, (None, 2))
    if seg.size and (np.any(seg[:, 0] < 0) or np.any(seg[:, 1] > T) or np.any(seg[:, 0] >= seg[:, 1])):
        _fail(filename, "/actions/segments", f"each row must be [start, stop) with 0 <= start < stop <= {T}")
    par = np.asarray(run.actions.params, float)
    if par.ndim != 2 or par.shape[0] != seg.shape[0]:
        _fail(filename, "/actions/params", f"expected shape ({seg.shape[0]}, n), got {par.shape}")
    _check_finite(filename, "/actions/params", par)


def _validate_scene_and_prior(run: Run, filename) -> None:
    """The ground (/scene attrs ground_normal a unit vector, ground_height finite and
    plausible) and the /prior attrs initial_pose and size_bound."""
    D = run.dim
    gn = run.up
    _check_shape(filename, "/scene attrs ground_normal", gn, (D,))
    if abs(np.linalg.norm(gn) - 1.0) > UNIT_NORM_TOL:
        _fail(filename, "/scene attrs ground_normal", "must be a unit vector")
    if not np.isfinite(run.ground_height):
        _fail(filename, "/scene attrs ground_height", "must be finite")
    check_plausible(filename, "/scene attrs ground_height", run.ground_height, MAX_ABS_POSITION, "m",
                    "MAX_ABS_POSITION")
    if "initial_pose" in run.prior:
        ip = np.asarray(run.prior["initial_pose"], float)
        _check_shape(filename, "/prior attrs initial_pose", ip, (pose_size(D),))
        _check_finite(filename, "/prior attrs initial_pose", ip)
    if "size_bound" in run.prior:
        sb = float(run.prior["size_bound"])
        if not (np.isfinite(sb) and sb > 0):
            _fail(filename, "/prior attrs size_bound", f"must be > 0, got {sb}")


def _validate_truth(run: Run, filename, T: int) -> None:
    """/truth/pose (T, P) and /truth/vertices (K, D)."""
    D = run.dim
    _check_shape(filename, "/truth/pose", np.asarray(run.truth.pose), (T, pose_size(D)))
    _check_shape(filename, "/truth/vertices", np.asarray(run.truth.vertices), (None, D))


# ---------------------------------------------------------------------------------
# reading


def read_run(path) -> Run:
    """Read and validate a run file.

    Raises
    ------
    TacestError / FileFormatError : missing file, not HDF5, or anything against SPEC;
        the message names the file and the offending path.
    """
    notes = []  # shown once the whole file is valid (a bad file gets one line: its error)
    with open_h5(path) as f:
        r = Reader(f, path)
        fmt = attr_str(r.attr("/", "format"))
        if fmt != FORMAT:
            r.fail("attrs format", f"expected {FORMAT!r}, got {fmt!r}")
        version = r.attr_int("/", "version")
        if version != VERSION:
            r.fail("attrs version", f"unknown version {version} (this tacest reads version {VERSION})")
        dim = r.attr_int("/", "dim")
        if dim not in (2, 3):
            r.fail("attrs dim", f"must be 2 or 3, got {dim}")
        dt = r.attr_float("/", "dt", positive=True)
        gravity = r.attr_vector("/", "gravity", dim)
        source = attr_str(r.attr("/", "source", "unknown"))
        time = r.dataset("/time", (None,))
        T = time.shape[0]
        run = Run(dim=dim, dt=dt, time=time, gravity=gravity, source=source, filename=str(path))
        if r.has("/robot"):
            run.finger_position = r.dataset("/robot/finger_position", (T, None, dim))
            F = run.finger_position.shape[1]
            run.finger_radius = r.dataset("/robot/finger_radius", (F,))
        if r.has("/tactile"):
            if run.finger_position is None:
                r.fail("/robot", "required when /tactile is present")
            F = run.finger_position.shape[1]
            c = r.dataset("/tactile/contact", (T, F), dtype=float)
            if not np.all(np.isin(c, (0.0, 1.0))):
                r.fail("/tactile/contact", "values must be 0 or 1")
            run.contact = c.astype(np.uint8)
            run.normal = r.dataset("/tactile/normal", (T, F, dim), allow_nan=True)
            if r.has("/tactile/force"):
                run.force = r.dataset("/tactile/force", (T, F, dim))
        if r.has("/observations"):
            run.pose_obs = r.dataset("/observations/pose", (T, pose_size(dim)), allow_nan=True)
            missing = [n for n in ("sigma_position", "sigma_angle")
                       if n not in f["/observations/pose"].attrs and n not in f["/observations"].attrs]
            if missing:
                notes.append(f"note: {path}: /observations/pose has no {' or '.join(missing)}; using "
                             f"{DEFAULT_SIGMA_POSITION} m / {DEFAULT_SIGMA_ANGLE} rad")
            for name, default in (("sigma_position", DEFAULT_SIGMA_POSITION),
                                  ("sigma_angle", DEFAULT_SIGMA_ANGLE)):
                holder = "/observations/pose" if name in f["/observations/pose"].attrs else "/observations"
                setattr(run, name, r.attr_float(holder, name, default, positive=True))
        if r.has("/quality/missing"):
            run.missing = r.dataset("/quality/missing", (T,), dtype=float).astype(np.uint8)
        if r.has("/quality/missing_finger"):
            if run.finger_position is None:
                r.fail("/quality/missing_finger", "needs /robot (it is per finger)")
            mf = r.dataset("/quality/missing_finger", (T, run.finger_position.shape[1]), dtype=float)
            if not np.all(np.isin(mf, (0.0, 1.0))):
                r.fail("/quality/missing_finger", "values must be 0 or 1")
            run.missing_finger = mf.astype(np.uint8)
        if r.has("/actions"):
            seg = r.dataset("/actions/segments", (None, 2), dtype=float)
            if np.any(seg != np.round(seg)):
                r.fail("/actions/segments", "must be integers")
            if seg.size and (seg.min() < 0 or seg.max() > T):
                r.fail("/actions/segments", f"each row must be [start, stop) with 0 <= start < stop <= {T}")
            params = r.dataset("/actions/params", (seg.shape[0], None))
            kind = attr_str(r.attr("/actions/params", "kind", "poke"))
            names = [attr_str(n) for n in np.atleast_1d(r.attr("/actions/params", "names", np.array([])))]
            run.actions = Actions(segments=seg.astype(np.int64), params=params, kind=kind, names=names)
        if r.has("/scene"):
            run.ground_height = r.attr_float("/scene", "ground_height", 0.0)
            gn = r.attr_vector("/scene", "ground_normal", dim, None)
            run.ground_normal = gn
        if r.has("/prior"):
            prior = {}
            attrs = f["/prior"].attrs
            if "initial_pose" in attrs:
                prior["initial_pose"] = r.attr_vector("/prior", "initial_pose", pose_size(dim))
            if "size_bound" in attrs:
                prior["size_bound"] = r.attr_float("/prior", "size_bound", positive=True)
            if "shape" in attrs:
                prior["shape"] = attr_str(attrs["shape"])
            for k in attrs:
                if k not in prior:
                    prior[k] = attrs[k]
            run.prior = prior
        if r.has("/truth"):
            run.truth = _read_truth(r, f, dim, T)
        for k, v in f.attrs.items():
            if k not in ("format", "version", "dim", "dt", "gravity", "source", *PROVENANCE_ATTRS):
                run.extra_attrs[k] = v
    _validate(run, path)
    for note in notes:
        print(note, file=sys.stderr)
    run.sha256 = sha256_file(path)
    return run


def run_sha256(run: Run) -> str:
    """The SHA-256 of the file ``run`` came from: the one taken when it was read, else
    the file's own (read now); "" for a run that came from no file, or whose file is not
    there to read (a run made in memory and named, e.g. a sub-run cut from another)."""
    import os

    if not run.filename:
        return ""
    if run.sha256:
        return run.sha256
    return sha256_file(run.filename) if os.path.isfile(run.filename) else ""


def read_runs(paths) -> list:
    """Read and validate the run files of one object (:func:`read_run` each).

    The same run given twice — the same file, or a copy of it (equal SHA-256) — is an
    error: its samples would count twice.
    """
    from tacest.errors import TacestError

    runs, seen = [], {}
    for path in paths:
        run = read_run(path)
        sha = run.sha256
        if sha in seen:
            raise TacestError(f"{path}: is the same run as {seen[sha]} (SHA-256 {sha[:12]}...); give each run once")
        seen[sha] = path
        runs.append(run)
    return runs


def _is_number_or_numbers(v) -> bool:
    if isinstance(v, list):
        return all(_is_number_or_numbers(x) for x in v)
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _read_truth(r: Reader, f, dim, T) -> Truth:
    pose = r.dataset("/truth/pose", (T, pose_size(dim)))
    vertices = r.dataset("/truth/vertices", (None, dim))
    mass = r.attr_float("/truth", "mass", float("nan"))
    if dim == 2:
        inertia = r.attr_float("/truth", "inertia", float("nan"))
    else:
        raw = r.attr("/truth", "inertia", None)
        inertia = None if raw is None else np.asarray(raw, float).reshape(3, 3)
    fg = r.attr_float("/truth", "friction_ground", float("nan"))
    ff = r.attr_float("/truth", "friction_finger", float("nan"))
    eff_raw = r.attr("/truth", "effects", "[]")
    try:
        effects = json.loads(attr_str(eff_raw))
    except json.JSONDecodeError:
        r.fail("/truth attrs effects", "not valid JSON")
    if isinstance(effects, dict):
        effects = [effects]
    for e in effects if isinstance(effects, list) else [None]:
        if not (isinstance(e, dict) and isinstance(e.get("name"), str) and all(
                _is_number_or_numbers(v) for k, v in e.items() if k != "name")):
            r.fail("/truth attrs effects", f"expected {{\"name\": str, parameter: number, ...}} objects, got {e!r}"[:200])
    return Truth(pose=pose, vertices=vertices, mass=mass, inertia=inertia,
                 friction_ground=fg, friction_finger=ff, effects=effects)


# ---------------------------------------------------------------------------------
# writing


def write_run(run: Run, path, include_truth: bool = True) -> None:
    """Validate ``run`` and write it atomically to ``path`` (SPEC v1)."""
    _validate(run, path)
    with atomic_h5(path) as f:
        fill_run_file(f, run, include_truth=include_truth)


def write_provenance(f, blind: bool = False) -> None:
    """Root attrs ``tacest_version`` and ``command_line`` (tacest.provenance).  A blind
    run (a simulated run written without its /truth) must not give its answer away: its
    command line and the simulator's ``sim_options`` (which name the injected effects and
    the seed that reproduces the truth) are replaced by their SHA-256,
    ``command_line_sha256`` and ``sim_options_sha256`` (docs/formats.md, "Provenance")."""
    prov = provenance()
    f.attrs["tacest_version"] = prov["tacest_version"]
    if not blind:
        f.attrs["command_line"] = prov["command_line"]
        return
    f.attrs["command_line_sha256"] = sha256_text(prov["command_line"])
    for key in ("command_line", "sim_options"):
        if key in f.attrs:
            if key == "sim_options":
                f.attrs["sim_options_sha256"] = sha256_text(attr_str(f.attrs[key]))
            del f.attrs[key]


def fill_run_file(f, run: Run, include_truth: bool = True) -> None:
    """Write every group of ``run`` into an open, empty h5py File (no validation), with
    the provenance attrs (:func:`write_provenance`)."""
    f.attrs["format"] = FORMAT
    f.attrs["version"] = VERSION
    f.attrs["dim"] = int(run.dim)
    f.attrs["dt"] = float(run.dt)
    f.attrs["gravity"] = np.asarray(run.gravity, float)
    f.attrs["source"] = str(run.source)
    for k, v in run.extra_attrs.items():
        f.attrs[k] = v
    write_provenance(f, blind=include_truth is False and run.truth is not None)
    f.create_dataset("time", data=np.asarray(run.time, float))
    if run.finger_position is not None:
        g = f.create_group("robot")
        g.create_dataset("finger_position", data=np.asarray(run.finger_position, float))
        g.create_dataset("finger_radius", data=np.asarray(run.finger_radius, float))
    if run.contact is not None:
        g = f.create_group("tactile")
        g.create_dataset("contact", data=np.asarray(run.contact, np.uint8))
        g.create_dataset("normal", data=np.asarray(run.normal, float))
        if run.force is not None:
            g.create_dataset("force", data=np.asarray(run.force, float))
    if run.pose_obs is not None:
        g = f.create_group("observations")
        d = g.create_dataset("pose", data=np.asarray(run.pose_obs, float))
        d.attrs["sigma_position"] = float(run.sigma_position)
        d.attrs["sigma_angle"] = float(run.sigma_angle)
    if run.missing is not None or run.missing_finger is not None:
        g = f.create_group("quality")
        if run.missing is not None:
            g.create_dataset("missing", data=np.asarray(run.missing, np.uint8))
        if run.missing_finger is not None:
            g.create_dataset("missing_finger", data=np.asarray(run.missing_finger, np.uint8))
    if run.actions is not None:
        g = f.create_group("actions")
        g.create_dataset("segments", data=np.asarray(run.actions.segments, np.int64).reshape(-1, 2))
        d = g.create_dataset("params", data=np.asarray(run.actions.params, float))
        d.attrs["kind"] = run.actions.kind
        d.attrs["names"] = np.array([str(n) for n in run.actions.names], dtype=object) \
            if run.actions.names else np.array([], dtype="S1")
    g = f.create_group("scene")
    g.attrs["ground_height"] = float(run.ground_height)
    g.attrs["ground_normal"] = run.up
    if run.prior:
        g = f.create_group("prior")
        for k, v in run.prior.items():
            g.attrs[k] = v
    if include_truth and run.truth is not None:
        tr = run.truth
        g = f.create_group("truth")
        g.create_dataset("pose", data=np.asarray(tr.pose, float))
        g.create_dataset("vertices", data=np.asarray(tr.vertices, float))
        g.attrs["mass"] = float(tr.mass)
        g.attrs["inertia"] = np.asarray(tr.inertia, float) if run.dim == 3 else float(tr.inertia)
        g.attrs["friction_ground"] = float(tr.friction_ground)
        g.attrs["friction_finger"] = float(tr.friction_finger)
        g.attrs["effects"] = json.dumps(tr.effects, sort_keys=True)

"""``tacest record --source video``: a run file from a tactile dome camera and a finger log.

Inputs (all documented in docs/tactile_video.md):

- frames: a folder of images (png, jpg, jpeg, bmp, tif, tiff, pgm, ppm) or a video file.
  Frame times: a folder's ``timestamps.csv`` (header ``file,t`` or ``t``; s), else
  ``t0 + k / fps`` with ``--fps``; a video file: ``t0 + k / fps`` with the container's
  frame rate unless ``--fps`` is given.  Colour frames are converted to grey.
- calibration JSON: :mod:`tacest.sensors.dome`.
- finger log CSV: header ``t,x,y[,z][,finger][,qw,qx,qy,qz]``: time (s, the frames'
  clock), fingertip centre (m, world frame; dim 2 with x,y, dim 3 with x,y,z), optional
  finger index (one value only: a camera watches one finger) and optional per-sample
  finger orientation (unit quaternion, scalar first, finger frame to world), which
  overrides the calibration's fixed rotation.

Output: a SPEC run, ``source = "video"``, one finger, contact and normal only (no force
stream: the flow gives no calibrated force).  Its dim is the finger log's: with ``x,y``
columns a 2-D run (what ``tacest estimate`` takes today), with ``x,y,z`` a 3-D run.  In
2-D the world is the (x, y) plane of the 3-D world frame: the dome normal, computed in
3-D, is projected onto it and renormalised; its out-of-plane (z) component is discarded
(reported as a tilt angle in ``video_settings``) and a contact whose normal is nearly
perpendicular to the plane is dropped (:data:`MIN_INPLANE_NORM`).  The time grid is uniform with dt = the
median frame interval, from the first frame inside the finger log's time span to the last
one; each sample takes the frames within +-dt/2 of its time (exactly one when the camera
is regular), finger positions are linearly interpolated onto the sample times and
orientations spherically (slerp).  A sample with no frame within +-dt/2 (a dropped frame)
is marked in ``/quality/missing`` with contact 0 and NaN normal.
"""

from __future__ import annotations

import logging

import csv
import json
import queue
import re
import threading
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Optional

import numpy as np

from tacest.constants import STANDARD_GRAVITY
from tacest.errors import TacestError
from tacest.sensors.dome import DomeCalibration, load_calibration
from tacest.sensors.tactile_flow import DetectSettings, FlowSettings, TactileFlow, decide_contacts

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
TIMESTAMPS_NAME = "timestamps.csv"

#: In a 2-D run, a contact whose normal has less than this in-plane length (before
#: renormalising) is dropped: the normal is within ~11.5 deg of perpendicular to the
#: world plane, so its in-plane direction is mostly noise.
MIN_INPLANE_NORM = 0.2

#: Quaternions in the finger log must have |q| within this of 1 (6 decimals in a CSV
#: give ~1e-6; hand-typed 4-decimal values ~1e-4).
QUAT_NORM_TOL = 1e-3

#: Frames may jitter by this fraction of dt and still count as uniform in the report.
UNIFORM_JITTER = 0.05



@dataclass
class VideoOptions:
    """Options of the video recorder.

    fps : frame rate (Hz) when there is no timestamps.csv, or to override a video's own
    t0 : time (s) of the first frame when times come from the frame rate
    reference : path of a no-contact reference image; None: the first frame
    flow, detect : see tactile_flow.FlowSettings / DetectSettings
    """

    fps: Optional[float] = None
    t0: float = 0.0
    reference: Optional[str] = None
    flow: FlowSettings = field(default_factory=FlowSettings)
    detect: DetectSettings = field(default_factory=DetectSettings)


@dataclass
class FingerLog:
    """t : (M,) s, strictly increasing; position : (M, D) m; quat : (M, 4) or None."""

    t: np.ndarray
    position: np.ndarray
    quat: Optional[np.ndarray] = None

    @property
    def dim(self) -> int:
        return int(self.position.shape[1])


@dataclass
class FrameSource:
    """times : (N,) s; names : list of N labels (file names or "frame k");
    open() -> iterator of (H, W) uint8 grey frames."""

    times: np.ndarray
    names: list
    open: Callable[[], Iterator[np.ndarray]]
    description: str


# ---------------------------------------------------------------------------------
# finger log


def read_finger_log(path) -> FingerLog:
    """Read and validate a finger log CSV (see the module docstring)."""
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except OSError as exc:
        raise TacestError(f"{path}: cannot read finger log ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise TacestError(f"{path}: not a text CSV file") from None
    if not rows:
        raise TacestError(f"{path}: empty finger log")
    header = [h.strip().lower() for h in rows[0]]
    known = {"t", "x", "y", "z", "finger", "qw", "qx", "qy", "qz"}
    for h in header:
        if h not in known:
            raise TacestError(f"{path}: unknown column {h!r} (expected t,x,y[,z][,finger][,qw,qx,qy,qz])")
    if len(set(header)) != len(header):
        raise TacestError(f"{path}: repeated column in header {','.join(header)}")
    for need in ("t", "x", "y"):
        if need not in header:
            raise TacestError(f"{path}: missing column {need!r} (header must be t,x,y[,z][,finger][,qw,qx,qy,qz])")
    qcols = [c for c in ("qw", "qx", "qy", "qz") if c in header]
    if qcols and len(qcols) != 4:
        raise TacestError(f"{path}: orientation needs all four columns qw,qx,qy,qz")
    data = np.empty((len(rows) - 1, len(header)))
    for i, r in enumerate(rows[1:]):
        if len(r) != len(header):
            raise TacestError(f"{path}: line {i + 2}: expected {len(header)} fields, got {len(r)}")
        try:
            data[i] = [float(c) for c in r]
        except ValueError:
            raise TacestError(f"{path}: line {i + 2}: not a number in {','.join(r)!r}") from None
    if data.shape[0] < 2:
        raise TacestError(f"{path}: needs at least 2 samples, got {data.shape[0]}")
    if not np.all(np.isfinite(data)):
        i = int(np.argwhere(~np.all(np.isfinite(data), axis=1))[0][0])
        raise TacestError(f"{path}: line {i + 2}: NaN or inf")
    col = {h: data[:, k] for k, h in enumerate(header)}
    t = col["t"]
    if np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0)) + 1
        raise TacestError(f"{path}: line {i + 2}: time stamps must be strictly increasing "
                          f"({t[i]} after {t[i - 1]})")
    if "finger" in col and np.unique(col["finger"]).size > 1:
        raise TacestError(f"{path}: finger column has several fingers; a tactile camera watches one "
                          "(split the log per finger)")
    axes = ["x", "y", "z"] if "z" in col else ["x", "y"]
    pos = np.stack([col[a] for a in axes], 1)
    quat = None
    if qcols:
        quat = np.stack([col[c] for c in ("qw", "qx", "qy", "qz")], 1)
        qn = np.linalg.norm(quat, axis=1)
        if np.any(np.abs(qn - 1.0) > QUAT_NORM_TOL):
            i = int(np.argmax(np.abs(qn - 1.0) > QUAT_NORM_TOL))
            raise TacestError(f"{path}: line {i + 2}: quaternion qw,qx,qy,qz is not unit length (|q| = {qn[i]:.6g})")
        quat = quat / qn[:, None]
    return FingerLog(t=t, position=pos, quat=quat)


# ---------------------------------------------------------------------------------
# frames


def _natural_key(name: str):
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name)]


def _read_grey(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise TacestError(f"{path}: cannot read image (not an image file, or corrupt)")
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.dtype != np.uint8:  # 16-bit images: keep the top 8 bits
        img = (img.astype(np.float64) * (255.0 / np.iinfo(img.dtype).max if img.dtype.kind == "u" else 1.0))
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def _read_timestamps(path: Path, image_names: list):
    """timestamps.csv -> (names, times)."""
    try:
        with open(path, newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError) as exc:
        raise TacestError(f"{path}: cannot read ({exc})") from None
    if not rows:
        raise TacestError(f"{path}: empty")
    header = [h.strip().lower() for h in rows[0]]
    if "t" not in header or any(h not in ("t", "file") for h in header):
        raise TacestError(f"{path}: header must be 'file,t' or 't', got {','.join(rows[0])!r}")
    it, jf = header.index("t"), header.index("file") if "file" in header else None
    names, times = [], []
    for i, r in enumerate(rows[1:]):
        if len(r) != len(header):
            raise TacestError(f"{path}: line {i + 2}: expected {len(header)} fields, got {len(r)}")
        try:
            times.append(float(r[it]))
        except ValueError:
            raise TacestError(f"{path}: line {i + 2}: time {r[it]!r} is not a number") from None
        if jf is not None:
            names.append(r[jf].strip())
    times = np.asarray(times)
    if jf is None:
        if len(times) != len(image_names):
            raise TacestError(f"{path}: {len(times)} time stamps for {len(image_names)} images "
                              "(add a 'file' column to name the frames)")
        names = list(image_names)
    if not np.all(np.isfinite(times)):
        raise TacestError(f"{path}: time stamps must be finite numbers")
    if np.any(np.diff(times) <= 0):
        i = int(np.argmax(np.diff(times) <= 0)) + 1
        raise TacestError(f"{path}: line {i + 2}: time stamps must be strictly increasing")
    return names, times


def _prefetch(items, load, depth: int = 8):
    """Iterate load(item) for items, decoding up to ``depth`` ahead in a thread (image
    decoding releases the GIL, so it overlaps with the flow on the other core)."""
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    sentinel = object()

    def work():
        try:
            for it in items:
                if stop.is_set():
                    return
                q.put(load(it))
        except BaseException as exc:  # handed to the consumer, raised there
            q.put(exc)
        q.put(sentinel)

    th = threading.Thread(target=work, daemon=True)
    th.start()
    try:
        while True:
            x = q.get()
            if x is sentinel:
                return
            if isinstance(x, BaseException):
                raise x
            yield x
    finally:
        stop.set()
        while th.is_alive():  # unblock a producer waiting on a full queue
            try:
                q.get_nowait()
            except queue.Empty:
                th.join(0.01)


def open_frames(frames, fps: Optional[float] = None, t0: float = 0.0) -> FrameSource:
    """Find the frames and their time stamps (see the module docstring).  Nothing is
    decoded yet except, for a video, the container's properties."""
    p = Path(frames)
    if not p.exists():
        raise TacestError(f"{p}: no such file or folder")
    if p.is_dir():
        images = sorted((q.name for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES and q.is_file()),
                        key=_natural_key)
        ts = p / TIMESTAMPS_NAME
        if ts.exists():
            names, times = _read_timestamps(ts, images)
            for n in names:
                if not (p / n).is_file():
                    raise TacestError(f"{ts}: frame file {n!r} does not exist")
            how = f"time stamps from {TIMESTAMPS_NAME}"
        else:
            if not images:
                raise TacestError(f"{p}: no image files ({', '.join(IMAGE_SUFFIXES)}) in the folder")
            if fps is None:
                raise TacestError(f"{p}: no {TIMESTAMPS_NAME} in the folder; give the frame rate with --fps")
            names = images
            times = t0 + np.arange(len(names)) / fps
            how = f"t = {t0} s + k / {fps} Hz"
        if len(names) < 2:
            raise TacestError(f"{p}: needs at least 2 frames, found {len(names)}")
        paths = [p / n for n in names]
        return FrameSource(times=np.asarray(times, float), names=list(names),
                           open=lambda: _prefetch(paths, _read_grey), description=f"{len(names)} images in {p} ({how})")
    return _open_video(p, fps, t0)


def _open_video(p: Path, fps, t0) -> FrameSource:
    import cv2

    cap = cv2.VideoCapture(str(p))
    ok = cap.isOpened()
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if ok else 0
    rate = fps if fps is not None else (cap.get(cv2.CAP_PROP_FPS) if ok else 0.0)
    cap.release()
    if not ok:
        raise TacestError(f"{p}: cannot open as a video (and it is not a folder of images)")
    if not (rate and np.isfinite(rate) and rate > 0):
        raise TacestError(f"{p}: the video has no frame rate; give it with --fps")
    if n < 2:
        # some containers do not report a count: count by decoding
        n = sum(1 for _ in _iter_video(p))
        if n < 2:
            raise TacestError(f"{p}: needs at least 2 frames, found {n}")
    times = t0 + np.arange(n) / rate
    return FrameSource(times=times, names=[f"frame {k}" for k in range(n)],
                       open=lambda: _prefetch(_iter_video(p), lambda img: img),
                       description=f"{n} frames of {p} (t = {t0} s + k / {rate:g} Hz)")


def _iter_video(p: Path):
    import cv2

    cap = cv2.VideoCapture(str(p))
    try:
        while True:
            ok, img = cap.read()
            if not ok:
                return
            if img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            yield img
    finally:
        cap.release()


# ---------------------------------------------------------------------------------
# the recorder


@dataclass
class VideoResult:
    """Per-frame analysis, kept for diagnostics and benchmarks.

    times : (N,) s; strength : (N,) px/px; uv : (N, 2) px; contact : (N,) bool
    """

    times: np.ndarray
    strength: np.ndarray
    uv: np.ndarray
    contact: np.ndarray
    noise: float
    threshold_on: float
    threshold_off: float


def analyse_frames(frame_iter, calib: DomeCalibration, options: VideoOptions, n_expected: int,
                   names: Optional[list] = None, reference: Optional[np.ndarray] = None):
    """Run the flow analysis over frames.  Returns (strength (N,), uv (N, 2), tracker)."""
    tracker = TactileFlow(calib, options.flow)
    W, H = calib.image_size
    strength = np.zeros(n_expected)
    uv = np.full((n_expected, 2), np.nan)
    k = -1
    for k, grey in enumerate(frame_iter):
        if k >= n_expected:  # a video container may under-report its frame count
            k = n_expected - 1
            break
        if grey.shape != (H, W):
            where = names[k] if names else f"frame {k}"
            raise TacestError(f"{where}: frame is {grey.shape[1]}x{grey.shape[0]} px, the calibration's "
                              f"image_size is {W}x{H}")
        if not tracker.has_reference:
            tracker.set_reference(grey if reference is None else reference)
        a = tracker.analyse(grey)
        strength[k] = a.strength
        uv[k] = a.uv
    if k + 1 < n_expected:
        raise TacestError(f"expected {n_expected} frames, could decode only {k + 1}")
    return strength, uv, tracker


def _frames_to_samples(ft, t_start, dt, T, dec, strength, uv):
    """(contact (T,) uint8, contact point uv (T, 2) px, missing (T,) bool): each sample
    takes the frames within ±dt/2 of its time, the strongest contact frame's point."""
    k_of = np.floor((ft - t_start) / dt + 0.5).astype(int)
    contact = np.zeros(T, np.uint8)
    uv_s = np.full((T, 2), np.nan)
    best = np.full(T, -np.inf)
    seen = np.zeros(T, bool)
    for j in range(len(ft)):
        k = k_of[j]
        if 0 <= k < T:
            seen[k] = True
            if dec.contact[j] and strength[j] > best[k]:
                contact[k] = 1
                best[k] = strength[j]
                uv_s[k] = uv[j]
    missing = ~seen
    return contact, uv_s, missing


def _finger_frames(flog, cal, time, contact, uv_s):
    """(finger positions (T, D) m, contact normals (T, D) world, 2-D out-of-plane tilt of
    the kept normals (deg) or None) at the sample times; contact samples whose normal
    is nearly perpendicular to a 2-D world plane are dropped from ``contact`` in place."""
    T = len(time)
    D = flog.dim
    pos = np.stack([np.interp(time, flog.t, flog.position[:, a]) for a in range(D)], 1)
    if flog.quat is not None:
        from scipy.spatial.transform import Rotation, Slerp

        rots = Slerp(flog.t, Rotation.from_quat(flog.quat, scalar_first=True))(np.clip(time, flog.t[0], flog.t[-1]))
        R = rots.as_matrix()
    else:
        R = np.broadcast_to(cal.rotation_world_from_finger, (T, 3, 3))
    normal = np.full((T, D), np.nan)
    on = contact.astype(bool)
    dropped = 0
    tilt = None  # 2-D: out-of-plane tilt of the kept normals before projection, deg
    if on.any():
        n, inplane = cal.object_normal(uv_s[on], R[on], dim=D)
        good = inplane >= MIN_INPLANE_NORM
        idx = np.flatnonzero(on)
        normal[idx[good]] = n[good]
        contact[idx[~good]] = 0
        dropped = int((~good).sum())
        if D == 2 and good.any():
            tilt = np.degrees(np.arccos(np.clip(inplane[good], 0.0, 1.0)))
    if dropped:
        log.warning(f"{dropped} contact sample(s) dropped: their normal is nearly perpendicular to the 2-D world plane")
    if tilt is not None:
        log.info(f"2-D run: contact normals projected onto the x-y plane; their out-of-plane tilt (discarded) "
                 f"median {np.median(tilt):.2f} deg, max {np.max(tilt):.2f} deg")
    return pos, normal, tilt


def record_video(frames, calib, finger_log, output=None, options: Optional[VideoOptions] = None):
    """Make a SPEC run from tactile frames and a finger log; write it to ``output`` if given.

    Parameters
    ----------
    frames : path of a folder of images or of a video file
    calib : path of a dome calibration JSON, or a DomeCalibration
    finger_log : path of a finger log CSV, or a FingerLog
    output : path of the run file to write (None: do not write)
    options : VideoOptions

    Returns
    -------
    (Run, VideoResult)
    """
    from tacest.io.run import Run, write_run

    opts = options or VideoOptions()
    opts.flow.check()
    opts.detect.check()
    if opts.fps is not None and not (np.isfinite(opts.fps) and opts.fps > 0):
        raise TacestError(f"--fps must be > 0, got {opts.fps}")
    cal = calib if isinstance(calib, DomeCalibration) else load_calibration(calib)
    flog = finger_log if isinstance(finger_log, FingerLog) else read_finger_log(finger_log)
    if cal.rotation_world_from_finger is None and flog.quat is None:
        raise TacestError("no finger orientation: put rotation_world_from_finger in the calibration "
                          "or qw,qx,qy,qz columns in the finger log")
    src = open_frames(frames, fps=opts.fps, t0=opts.t0)
    ref_img = None
    if opts.reference is not None:
        ref_img = _read_grey(Path(opts.reference))
        W, H = cal.image_size
        if ref_img.shape != (H, W):
            raise TacestError(f"{opts.reference}: reference image is {ref_img.shape[1]}x{ref_img.shape[0]} px, "
                              f"the calibration's image_size is {W}x{H}")

    # the run's uniform grid, checked before any decoding
    ft = src.times
    dt = float(np.median(np.diff(ft)))
    t_lo, t_hi = max(ft[0], flog.t[0]), min(ft[-1], flog.t[-1])
    eps = 1e-6 * dt
    inside = np.flatnonzero((ft >= t_lo - eps) & (ft <= t_hi + eps))
    if inside.size < 2:
        raise TacestError(f"frames (t = {ft[0]:.6g}..{ft[-1]:.6g} s) and finger log (t = {flog.t[0]:.6g}.."
                          f"{flog.t[-1]:.6g} s) overlap in {inside.size} frame(s), need 2; are they on one clock?")
    t_start = ft[inside[0]]
    T = int(np.floor((min(t_hi, ft[inside[-1]]) - t_start) / dt + 1e-6)) + 1
    if T < 2:
        raise TacestError("the overlap of frames and finger log is shorter than two frame intervals")
    time = t_start + dt * np.arange(T)
    jitter = float(np.max(np.abs(np.diff(ft) - dt)))

    # (progress is reported after the analysis, so a bad frame fails with one line only)
    strength, uv, tracker = analyse_frames(src.open(), cal, opts, len(ft), src.names, ref_img)
    log.info(f"video: {src.description}; dt = {dt * 1e3:.3f} ms"
             + (f" (frame times jitter up to {jitter * 1e3:.3f} ms; resampled to a uniform grid)"
                if jitter > UNIFORM_JITTER * dt else ""))
    first_noise = 1 if ref_img is None else 0
    dec = decide_contacts(strength, opts.detect, first_noise_frame=first_noise)
    if dec.contact[first_noise:first_noise + opts.detect.noise_frames].any():
        log.warning("contact detected among the noise frames at the start; they should be free of contact")

    contact, uv_s, missing = _frames_to_samples(ft, t_start, dt, T, dec, strength, uv)
    pos, normal, tilt = _finger_frames(flog, cal, time, contact, uv_s)
    D = flog.dim

    settings = {"flow": tracker.settings_dict(), "detect": asdict(opts.detect), "fps": opts.fps, "t0": opts.t0,
                "reference": opts.reference or "first frame", "noise_level": dec.noise,
                "threshold_on": dec.threshold_on, "threshold_off": dec.threshold_off,
                "frames": str(frames), "n_frames": int(len(ft)), "frame_jitter_s": jitter}
    if tilt is not None:
        settings["normal_out_of_plane_deg"] = {"median": float(np.median(tilt)), "max": float(np.max(tilt))}
    run = Run(dim=D, dt=dt, time=time, gravity=np.r_[np.zeros(D - 1), -STANDARD_GRAVITY], source="video",
              finger_position=pos[:, None, :], finger_radius=np.array([cal.finger_radius]),
              contact=contact[:, None], normal=normal[:, None, :],
              missing=missing.astype(np.uint8) if missing.any() else None,
              extra_attrs={"video_settings": json.dumps(settings, sort_keys=True),
                           "dome_calibration": cal.to_json()})
    result = VideoResult(times=ft, strength=strength, uv=uv, contact=dec.contact, noise=dec.noise,
                         threshold_on=dec.threshold_on, threshold_off=dec.threshold_off)
    if output is not None:
        write_run(run, output)
    log.info(f"{'wrote ' + str(output) if output is not None else 'recorded'}: {T} samples, dim {D}, "
             f"contact in {int(contact.sum())}; noise level {dec.noise:.4g}, thresholds on {dec.threshold_on:.4g} / "
             f"off {dec.threshold_off:.4g}"
             + (f"; {int(missing.sum())} sample(s) without a frame" if missing.any() else ""))
    return run, result

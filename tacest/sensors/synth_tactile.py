"""Synthetic tactile dome image sequences with known contacts (for tests and benchmarks).

A dome image (default 640 x 480) carries a random dot pattern (jittered grid of bright
Gaussian dots on a vignetted grey membrane, dark outside the rim).  Contacts come in
on/off periods; during a contact the dots are displaced by a known indentation field at
a known image point (u0, v0)::

    d(p) = taper(rho) * [ g(r) r_hat + shear * exp(-r^2 / (2 s^2)) ],   r = |p - (u0, v0)|
    g(r) = A (r / s) exp((1 - r^2 / s^2) / 2)     (radial, outwards; peak A at r = s)

so the flow has a source (div > 0) at the contact; ``taper`` takes the displacement to
zero at the rim (the membrane is clamped there).  The indentation depth ramps up and
down over ``ramp_frames`` frames at the start and end of each contact (truth: contact on
all of them).  Lighting: Gaussian pixel noise, a slow gain and offset drift, a slowly
turning brightness gradient, and a brightening of the contact patch (shading).

The truth normal of a contact is computed exactly as the recorder is documented to do
(docs/tactile_video.md): the contact's polar and azimuth angles on the dome give the
fingertip's outward normal n_f (finger frame); the object normal is -R_wf n_f, projected
onto the world (x, y) plane in 2-D.

Scenes (``SynthConfig.scene``): ``wander`` (default) moves the finger along a slow
path that has nothing to do with the contacts (enough to test the image analysis);
``box-press`` (2-D only) is a poking scene the estimator can use: a box of
``box_size_m`` rests on the ground (y = 0, centred on x = 0) and the finger, its axis
along world +x, presses the box's left face head-on at a new height for each contact
(every contact at the dome's apex, so the object normal is (-1, 0)), indenting it by
``press_depth_m`` × depth and backing off by ``standoff_m`` between contacts.  Its finger
log is consistent with the images: the fingertip sphere overlaps the face exactly on the
contact frames.  The box does not move (a light press).

Outputs (:func:`write_sequence`): ``frames/frame_00000.png ...`` with
``frames/timestamps.csv`` (``file,t``), or ``frames.avi`` (MJPG) with ``--video``;
``calib.json``; ``fingers.csv`` (``t,x,y[,z]`` at ``finger_rate_hz``, starting before and
ending after the frames, on the same clock); ``truth.csv`` (``t,contact,nx,ny[,nz],u,v``
per frame; NaN normal and (u, v) without contact); for ``box-press`` also ``scene.json``
(the box's vertices, world frame, m, and the finger radius).

Command line: ``python -m tacest.sensors.synth_tactile OUT_DIR [--frames N] [--seed N]
[--dim 2|3] [--scene wander|box-press] [--size 640x480] [--noise SIGMA] [--video]``.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from tacest.sensors.dome import DomeCalibration

#: rotation_world_from_finger used by the generator.  3-D: the finger points down (its
#: axis z_f = world -z), image u = world x, image v = world -y.  2-D: the finger points
#: along world +x in the (x, y) plane, image u = world y (in the plane), image v = world z.
ROTATION_3D = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
ROTATION_2D = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

#: finger motions the generator can make (see the module docstring)
SCENES = ("wander", "box-press")


@dataclass
class SynthConfig:
    """Parameters of a synthetic sequence.  Lengths in px are full-resolution pixels; a
    value of None scales with the rim radius (so small test images keep the same look).

    width, height : image size, px
    n_frames, fps, t0 : frames at t0 + k / fps, s
    dim : 2 or 3 (world dimension of the finger log and the truth normals)
    rim_radius_px : default 0.46 * min(width, height)
    projection, rim_polar_angle_deg, dome_radius_m : the dome model (dome.py)
    dot_spacing_px : default rim / 20; dot_sigma_px : default 0.2 * spacing
    indent_amplitude_px : A, default 0.02 * rim; amplitude_range : per-contact factor range
    indent_radius_px : s, default 0.2 * rim
    shear_fraction : tangential displacement amplitude as a fraction of A (random direction)
    max_polar_deg : contacts are drawn with polar angle up to this
    lead_frames : contact-free frames at the start (>= the recorder's noise frames + 1)
    contact_frames, gap_frames : (min, max) lengths of contacts and of the gaps between
    ramp_frames : frames of partial depth at the start and the end of a contact
    noise_sigma : Gaussian pixel noise, grey levels (of 255)
    drift_gain, drift_offset, drift_period_s : slow lighting drift (relative gain, grey
        levels, period)
    gradient : amplitude of the slowly turning illumination gradient, grey levels
    shading : relative brightening of the contact patch at full depth
    finger_rate_hz, finger_lead_s : finger log rate and how long it starts before the
        first frame (and ends after the last)
    events : None (random schedule and locations), or a list of explicit contacts
        ``(start_frame, stop_frame, polar_deg, azimuth_deg)``: frames [start, stop), the
        contact point's polar angle on the dome and its azimuth in the image
        (atan2(v - v_c, u - u_c)); amplitude factor 1, no shear.  In ``box-press`` the
        scene decides where the dome is touched (the apex): give ``(start, stop)`` pairs
    scene : ``wander`` or ``box-press`` (2-D; see the module docstring)
    box_size_m : (width, height) of the box, m (box-press)
    press_depth_m : fingertip overlap with the face at full depth, m (box-press)
    standoff_m : gap between fingertip and face between contacts, m (box-press)
    """

    width: int = 640
    height: int = 480
    n_frames: int = 240
    fps: float = 30.0
    t0: float = 0.0
    dim: int = 3
    seed: int = 0
    rim_radius_px: Optional[float] = None
    projection: str = "equidistant"
    rim_polar_angle_deg: float = 90.0
    dome_radius_m: float = 0.012
    dot_spacing_px: Optional[float] = None
    dot_sigma_px: Optional[float] = None
    indent_amplitude_px: Optional[float] = None
    amplitude_range: tuple = (0.6, 1.4)
    indent_radius_px: Optional[float] = None
    shear_fraction: float = 0.2
    max_polar_deg: float = 60.0
    lead_frames: int = 15
    contact_frames: tuple = (15, 40)
    gap_frames: tuple = (10, 30)
    ramp_frames: int = 2
    noise_sigma: float = 3.0
    drift_gain: float = 0.06
    drift_offset: float = 6.0
    drift_period_s: float = 4.0
    gradient: float = 8.0
    shading: float = 0.08
    finger_rate_hz: float = 200.0
    finger_lead_s: float = 0.5
    events: Optional[list] = None
    scene: str = "wander"
    box_size_m: tuple = (0.10, 0.06)
    press_depth_m: float = 2e-4
    standoff_m: float = 5e-3


@dataclass
class SynthSequence:
    """A generated sequence and its truth.

    frames : (N, H, W) uint8 grey; times : (N,) s
    calib : DomeCalibration (with rotation_world_from_finger)
    finger_time : (M,) s; finger_position : (M, D) m, world frame
    contact : (N,) uint8; depth : (N,) float in [0, 1], fraction of the contact's amplitude
    normal : (N, D) unit object normal, world frame, NaN without contact
    contact_uv : (N, 2) px, NaN without contact
    box_vertices : (4, 2) m, world frame, counter-clockwise, for ``box-press``; else None
    """

    frames: np.ndarray
    times: np.ndarray
    calib: DomeCalibration
    finger_time: np.ndarray
    finger_position: np.ndarray
    contact: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    contact_uv: np.ndarray
    config: SynthConfig
    box_vertices: Optional[np.ndarray] = None

    @property
    def dim(self) -> int:
        return int(self.finger_position.shape[1])


def make_calibration(cfg: SynthConfig) -> DomeCalibration:
    """The dome calibration that matches ``cfg`` (centre of the image, rim radius)."""
    rim = cfg.rim_radius_px or 0.46 * min(cfg.width, cfg.height)
    return DomeCalibration(image_size=(cfg.width, cfg.height),
                           center_px=np.array([(cfg.width - 1) / 2.0, (cfg.height - 1) / 2.0]),
                           rim_radius_px=float(rim), dome_radius_m=cfg.dome_radius_m,
                           rim_polar_angle_deg=cfg.rim_polar_angle_deg, projection=cfg.projection,
                           finger_radius_m=cfg.dome_radius_m,
                           rotation_world_from_finger=ROTATION_3D if cfg.dim == 3 else ROTATION_2D)


def _schedule(cfg: SynthConfig, rng):
    """Contact events: list of (start, stop) frame indices [start, stop)."""
    events = []
    k = cfg.lead_frames
    while True:
        n = int(rng.integers(cfg.contact_frames[0], cfg.contact_frames[1] + 1))
        if k + n > cfg.n_frames - 2:
            break
        events.append((k, k + n))
        k += n + int(rng.integers(cfg.gap_frames[0], cfg.gap_frames[1] + 1))
    return events


def _dot_texture(cfg: SynthConfig, calib: DomeCalibration, rng) -> np.ndarray:
    import cv2

    W, H = cfg.width, cfg.height
    rim = calib.rim_radius_px
    spacing = cfg.dot_spacing_px or rim / 20.0
    sigma = cfg.dot_sigma_px or 0.2 * spacing
    # jittered grid of dot centres, rendered at 2x and blurred (anti-aliased dots)
    gx, gy = np.meshgrid(np.arange(-spacing, W + spacing, spacing), np.arange(-spacing, H + spacing, spacing))
    pts = np.stack([gx.ravel(), gy.ravel()], 1) + rng.uniform(-0.3, 0.3, (gx.size, 2)) * spacing
    canvas = np.zeros((2 * H, 2 * W), np.float32)
    ij = np.round(pts * 2 + 0.5).astype(int)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < 2 * W) & (ij[:, 1] >= 0) & (ij[:, 1] < 2 * H)
    canvas[ij[ok, 1], ij[ok, 0]] = 1.0
    canvas = cv2.GaussianBlur(canvas, (0, 0), 2 * sigma)
    canvas /= canvas.max()
    dots = cv2.resize(canvas, (W, H), interpolation=cv2.INTER_AREA)
    u = np.arange(W)[None, :] - calib.center_px[0]
    v = np.arange(H)[:, None] - calib.center_px[1]
    rho = np.hypot(u, v) / rim
    inside = np.clip((1.0 - rho) * rim / 2.0 + 0.5, 0.0, 1.0)  # 2 px soft rim edge
    membrane = 75.0 * (1.0 - 0.35 * rho ** 2) + 150.0 * dots
    return (12.0 + inside * (membrane - 12.0)).astype(np.float32)


def generate(cfg: SynthConfig | None = None) -> SynthSequence:
    """Generate a sequence (frames in memory) and its truth."""
    import cv2

    cfg = cfg or SynthConfig()
    if cfg.dim not in (2, 3):
        raise ValueError("dim must be 2 or 3")
    if cfg.scene not in SCENES:
        raise ValueError(f"scene must be one of {', '.join(SCENES)}, got {cfg.scene!r}")
    press = cfg.scene == "box-press"
    if press and cfg.dim != 2:
        raise ValueError("the box-press scene is 2-D (dim=2)")
    rng = np.random.default_rng(cfg.seed)
    calib = make_calibration(cfg)
    W, H, N = cfg.width, cfg.height, cfg.n_frames
    rim = calib.rim_radius_px
    A0 = cfg.indent_amplitude_px or 0.02 * rim
    s = cfg.indent_radius_px or 0.2 * rim
    base = _dot_texture(cfg, calib, rng)
    times = cfg.t0 + np.arange(N) / cfg.fps

    # per-frame contact state
    depth = np.zeros(N)
    event_of = np.full(N, -1)
    explicit = cfg.events is not None
    events = [(int(e[0]), int(e[1])) for e in cfg.events] if explicit else _schedule(cfg, rng)
    params = []
    for e, (a, b) in enumerate(events):
        if press:  # a flat face pressed head-on touches the dome at its apex
            theta, az = 0.0, 0.0
        elif explicit:
            theta, az = np.deg2rad(cfg.events[e][2]), np.deg2rad(cfg.events[e][3])
        else:
            theta = np.deg2rad(cfg.max_polar_deg) * np.sqrt(rng.uniform(0.0, 1.0))  # ~uniform over the cap
            if cfg.dim == 2:  # keep the normal mostly in the world plane (image u axis)
                az = rng.choice([0.0, np.pi]) + rng.uniform(-np.pi / 6, np.pi / 6)
            else:
                az = rng.uniform(-np.pi, np.pi)
        n_f = np.array([np.sin(theta) * np.cos(az), np.sin(theta) * np.sin(az), np.cos(theta)])
        uv = calib.pixel_of_finger_direction(n_f)
        amp = A0 if explicit else A0 * rng.uniform(*cfg.amplitude_range)
        shear_dir = rng.uniform(-np.pi, np.pi)
        shear_frac = 0.0 if explicit else cfg.shear_fraction
        shear = shear_frac * amp * np.array([np.cos(shear_dir), np.sin(shear_dir)])
        params.append((uv, amp, shear))
        n = b - a
        r = cfg.ramp_frames
        for k in range(a, b):
            i = k - a
            frac = min(1.0, (i + 1) / (r + 1), (n - i) / (r + 1)) if r > 0 else 1.0
            depth[k] = frac
            event_of[k] = e
    contact = (depth > 0).astype(np.uint8)
    normal = np.full((N, cfg.dim), np.nan)
    contact_uv = np.full((N, 2), np.nan)
    for k in np.flatnonzero(contact):
        uv = params[event_of[k]][0]
        contact_uv[k] = uv
        normal[k] = calib.object_normal(uv, dim=cfg.dim)[0]

    uu, vv = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    rho = np.hypot(uu - calib.center_px[0], vv - calib.center_px[1]) / rim
    taper = np.clip((1.0 - rho) / 0.15, 0.0, 1.0) ** 2  # membrane clamped at the rim
    frames = np.empty((N, H, W), np.uint8)
    phase = rng.uniform(0, 2 * np.pi, 3)
    for k in range(N):
        t = times[k] - cfg.t0
        img = base
        shade = 0.0
        if depth[k] > 0:
            uv, amp, shear = params[event_of[k]]
            du, dv = uu - uv[0], vv - uv[1]
            r2 = (du * du + dv * dv) / (s * s)
            g = depth[k] * amp * np.exp(0.5 * (1.0 - r2)) / s  # g(r) / r
            e = depth[k] * np.exp(-0.5 * r2)
            dx = taper * (g * du + shear[0] * e)
            dy = taper * (g * dv + shear[1] * e)
            # backward warp: the dot at p moves to p + d(p)  =>  I(x) ~ I0(x - d(x))
            img = cv2.remap(base, (uu - dx).astype(np.float32), (vv - dy).astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            shade = cfg.shading * e
        gain = 1.0 + cfg.drift_gain * np.sin(2 * np.pi * t / cfg.drift_period_s + phase[0])
        offset = cfg.drift_offset * np.sin(2 * np.pi * t / (1.7 * cfg.drift_period_s) + phase[1])
        ang = 2 * np.pi * t / (3.1 * cfg.drift_period_s) + phase[2]
        grad = cfg.gradient * ((uu - W / 2) * np.cos(ang) + (vv - H / 2) * np.sin(ang)) / max(W, H)
        out = img * (gain * (1.0 + shade)) + offset + grad
        if cfg.noise_sigma > 0:
            out = out + rng.normal(0.0, cfg.noise_sigma, (H, W)).astype(np.float32)
        frames[k] = np.clip(out + 0.5, 0, 255).astype(np.uint8)

    # finger log, on the frames' clock, longer than the frames
    M = int(np.ceil((N / cfg.fps + 2 * cfg.finger_lead_s) * cfg.finger_rate_hz)) + 1
    ft = cfg.t0 - cfg.finger_lead_s + np.arange(M) / cfg.finger_rate_hz
    box = None
    if press:
        fp, box = _box_press_path(cfg, calib.finger_radius, times, depth, event_of, len(events), ft, rng)
    else:  # a slow wandering path (m)
        tt = ft - cfg.t0
        fp = np.stack([0.02 * np.sin(0.5 * tt), 0.05 + 0.01 * np.cos(0.7 * tt), 0.10 + 0.005 * np.sin(0.3 * tt)],
                      1)[:, :cfg.dim]
    return SynthSequence(frames=frames, times=times, calib=calib, finger_time=ft, finger_position=fp,
                         contact=contact, depth=depth, normal=normal, contact_uv=contact_uv, config=cfg,
                         box_vertices=box)


def _box_press_path(cfg: SynthConfig, radius: float, times, depth, event_of, n_events: int, ft, rng):
    """Fingertip centre (M, 2) m at the finger log times ``ft`` for the box-press scene,
    and the box's vertices (4, 2) m, world frame.

    Key positions at the frame times: on a contact frame the sphere overlaps the left face
    (x = -w/2) by press_depth_m × depth, off contact it stands off by standoff_m; the
    height is drawn per contact in [0.25 h, 0.75 h] and changes half-way through the gap
    before the contact (while backed off).  Between frames the path is a monotone cubic
    (PCHIP: smooth, no overshoot into the face); before the first and after the last frame
    it holds.
    """
    from scipy.interpolate import PchipInterpolator

    w, h = cfg.box_size_m
    heights = rng.uniform(0.25 * h, 0.75 * h, max(n_events, 1))
    x_touch = -0.5 * w - radius  # centre of a sphere just touching the face
    x_key = np.where(depth > 0, x_touch + cfg.press_depth_m * depth, x_touch - cfg.standoff_m)
    # height: the current contact's; in a gap, the previous one's until half-way, then the next one's
    N = len(times)
    y_key = np.empty(N)
    on = np.flatnonzero(event_of >= 0)
    for k in range(N):
        if event_of[k] >= 0:
            y_key[k] = heights[event_of[k]]
            continue
        before, after = on[on < k], on[on > k]
        if after.size and (not before.size or (k - before[-1]) > (after[0] - k)):
            y_key[k] = heights[event_of[after[0]]]
        else:
            y_key[k] = heights[event_of[before[-1]]] if before.size else heights[0]
    tc = np.clip(ft, times[0], times[-1])
    fp = np.stack([PchipInterpolator(times, x_key)(tc), PchipInterpolator(times, y_key)(tc)], 1)
    box = np.array([[-0.5 * w, 0.0], [0.5 * w, 0.0], [0.5 * w, h], [-0.5 * w, h]])
    return fp, box


def write_sequence(seq: SynthSequence, out_dir, video: bool = False) -> dict:
    """Write frames, calib.json, fingers.csv and truth.csv into ``out_dir``; returns the
    paths (keys ``frames``, ``calib``, ``finger_log``, ``truth``)."""
    import cv2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    H, W = seq.frames.shape[1:]
    if video:
        frames_path = out / "frames.avi"
        wr = cv2.VideoWriter(str(frames_path), cv2.VideoWriter_fourcc(*"MJPG"), float(seq.config.fps), (W, H), False)
        if not wr.isOpened():
            raise RuntimeError("OpenCV cannot write an MJPG video here")
        for f in seq.frames:
            wr.write(f)
        wr.release()
    else:
        frames_path = out / "frames"
        frames_path.mkdir(exist_ok=True)
        with open(frames_path / "timestamps.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["file", "t"])
            for k, (f, t) in enumerate(zip(seq.frames, seq.times)):
                name = f"frame_{k:05d}.png"
                cv2.imwrite(str(frames_path / name), f, [cv2.IMWRITE_PNG_COMPRESSION, 1])
                w.writerow([name, repr(float(t))])
    calib_path = out / "calib.json"
    seq.calib.save(calib_path)
    axes = "xyz"[: seq.dim]
    log_path = out / "fingers.csv"
    with open(log_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", *axes])
        for t, p in zip(seq.finger_time, seq.finger_position):
            w.writerow([f"{t:.6f}", *(f"{x:.6f}" for x in p)])
    truth_path = out / "truth.csv"
    with open(truth_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "contact", *("n" + a for a in axes), "u", "v"])
        for k in range(len(seq.times)):
            w.writerow([repr(float(seq.times[k])), int(seq.contact[k]),
                        *(f"{x:.9g}" for x in seq.normal[k]), *(f"{x:.6g}" for x in seq.contact_uv[k])])
    paths = {"frames": frames_path, "calib": calib_path, "finger_log": log_path, "truth": truth_path}
    if seq.box_vertices is not None:
        scene_path = out / "scene.json"
        scene_path.write_text(json.dumps({"scene": seq.config.scene,
                                          "box_vertices_m": np.asarray(seq.box_vertices).tolist(),
                                          "finger_radius_m": seq.calib.finger_radius}) + "\n")
        paths["scene"] = scene_path
    return paths


def read_truth(path):
    """Read a truth.csv: returns (t (N,), contact (N,) uint8, normal (N, D), uv (N, 2))."""
    data = np.genfromtxt(path, delimiter=",", names=True)
    names = data.dtype.names
    normal = np.stack([data[n] for n in names if n in ("nx", "ny", "nz")], 1)
    return data["t"], data["contact"].astype(np.uint8), normal, np.stack([data["u"], data["v"]], 1)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m tacest.sensors.synth_tactile",
                                description="Write a synthetic tactile dome image sequence with truth.")
    p.add_argument("out_dir")
    p.add_argument("--frames", type=int, default=240, help="number of frames (default 240)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dim", type=int, choices=(2, 3), default=None,
                   help="world dimension (default 3; 2 with --scene box-press)")
    p.add_argument("--scene", choices=SCENES, default="wander",
                   help="finger motion: wander (default) or box-press (2-D: a finger pressing a box's side)")
    p.add_argument("--size", default="640x480", help="WIDTHxHEIGHT (default 640x480)")
    p.add_argument("--noise", type=float, default=3.0, help="pixel noise sigma, grey levels (default 3)")
    p.add_argument("--video", action="store_true", help="write frames.avi (MJPG) instead of PNG frames")
    a = p.parse_args(argv)
    try:
        w, h = (int(x) for x in a.size.lower().split("x"))
    except ValueError:
        p.error(f"--size must be WIDTHxHEIGHT, got {a.size!r}")
    dim = a.dim if a.dim is not None else (2 if a.scene == "box-press" else 3)
    if a.scene == "box-press" and dim != 2:
        p.error("--scene box-press is 2-D: use --dim 2 (or leave --dim out)")
    cfg = SynthConfig(width=w, height=h, n_frames=a.frames, fps=a.fps, seed=a.seed, dim=dim, noise_sigma=a.noise,
                      scene=a.scene)
    seq = generate(cfg)
    paths = write_sequence(seq, a.out_dir, video=a.video)
    print(f"wrote {a.out_dir}: {a.frames} frames {w}x{h}, {int(seq.contact.sum())} in contact; "
          f"tacest record --source video --frames {paths['frames']} --calib {paths['calib']} "
          f"--finger-log {paths['finger_log']} -o RUN.h5", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

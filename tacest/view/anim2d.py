"""2-D animations (GIF, MP4) of a Scene: the true shape (outline), the estimated shape
(filled), the fingertips with the path they have travelled, and at each contact the
contact point and the measured normal as an arrow.

GIF needs nothing beyond matplotlib (its PillowWriter); MP4 needs an ``ffmpeg`` binary
(on the PATH, or from the ``imageio-ffmpeg`` package, extra ``tacest[mp4]``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from tacest.errors import TacestError
from tacest.geometry.transforms import transform_points
from tacest.io.outputs import atomic_file
from tacest.view.scene import Scene, frame_indices

log = logging.getLogger(__name__)

#: m, length of a drawn normal arrow
NORMAL_LENGTH = 0.03
#: m, margin around everything drawn
VIEW_MARGIN = 0.03
#: colours: true shape, estimated shape, finger, contact
C_TRUE, C_EST, C_FINGER, C_CONTACT = "#2a7f2a", "#d9792b", "#2f5fb3", "#c0392b"


def _ffmpeg_path():
    import shutil

    exe = shutil.which("ffmpeg")
    if exe:
        return exe
    try:
        import imageio_ffmpeg

        return imageio_ffmpeg.get_ffmpeg_exe()
    except Exception:  # not installed, or no binary for this platform
        return None


def _bounds(sc: Scene) -> tuple:
    pts = []
    for V, pose in ((sc.true_vertices, sc.true_pose), (sc.est_vertices, sc.est_pose)):
        if pose is not None:
            pts.append(transform_points(pose, V, 2).reshape(-1, 2))
    if sc.finger_position is not None:
        pts.append(sc.finger_position.reshape(-1, 2))
    P = np.concatenate(pts)
    lo, hi = P.min(axis=0) - VIEW_MARGIN, P.max(axis=0) + VIEW_MARGIN
    lo[1] = min(lo[1], -0.01)  # the ground in view
    return lo, hi


def write_animation_2d(sc: Scene, path, fps: float = 20.0, max_frames: int = 300) -> int:
    """Write the animation of ``sc`` (2-D) to ``path`` (.gif or .mp4); returns the
    number of frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation
    from matplotlib.patches import Circle, Polygon

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise TacestError(f"{path}: a 2-D animation is .gif or .mp4")
    if suffix == ".mp4":
        exe = _ffmpeg_path()
        if exe is None:
            raise TacestError(f"{path}: MP4 needs ffmpeg (install it, or pip install imageio-ffmpeg); "
                              "a .gif needs nothing")
        matplotlib.rcParams["animation.ffmpeg_path"] = exe
    dt = float(np.median(np.diff(sc.time))) if sc.n_samples > 1 else 0.01
    idx = frame_indices(sc.n_samples, dt, fps, max_frames)
    lo, hi = _bounds(sc)
    fig, ax = plt.subplots(figsize=(7.0, 7.0 * max(0.35, min(1.2, (hi[1] - lo[1]) / (hi[0] - lo[0])))), dpi=90)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.axhspan(lo[1], 0.0, color="0.85", zorder=0)
    ax.axhline(0.0, color="0.4", lw=1)
    true_patch = est_patch = None
    if sc.true_pose is not None:
        true_patch = ax.add_patch(Polygon(np.zeros((3, 2)), closed=True, fill=False, ec=C_TRUE, lw=2,
                                          label="true shape", zorder=3))
    if sc.est_pose is not None:
        est_patch = ax.add_patch(Polygon(np.zeros((3, 2)), closed=True, fc=C_EST, ec=C_EST, alpha=0.45,
                                         label="estimated shape", zorder=2))
    fingers, paths, quiv, cpts = [], [], None, None
    if sc.finger_position is not None:
        F = sc.finger_position.shape[1]
        for f in range(F):
            fingers.append(ax.add_patch(Circle((0, 0), sc.finger_radius[f], fc=C_FINGER, alpha=0.6, zorder=4,
                                               label="finger" if f == 0 else None)))
            paths.append(ax.plot([], [], color=C_FINGER, lw=1, alpha=0.6, zorder=4,
                                 label="finger path" if f == 0 else None)[0])
        cpts = ax.scatter(np.zeros(F), np.zeros(F), s=25, c=C_CONTACT, zorder=6, label="contact")
        quiv = ax.quiver(np.zeros(F), np.zeros(F), np.zeros(F), np.zeros(F), color=C_CONTACT, angles="xy",
                         scale_units="xy", scale=1.0, width=0.005, zorder=6, label="normal")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.8)
    title = ax.set_title("")

    def draw(i):
        k = int(idx[i])
        if true_patch is not None:
            true_patch.set_xy(transform_points(sc.true_pose[k], sc.true_vertices, 2))
        if est_patch is not None:
            est_patch.set_xy(transform_points(sc.est_pose[k], sc.est_vertices, 2))
        if fingers:
            p = sc.finger_position[k]
            on = sc.contact[k]
            n = np.where(on[:, None], np.nan_to_num(sc.normal[k]), 0.0)
            for f, c in enumerate(fingers):
                c.center = tuple(p[f])
                paths[f].set_data(sc.finger_position[:k + 1, f, 0], sc.finger_position[:k + 1, f, 1])
            touch = p - sc.finger_radius[:, None] * n  # the contact point on the finger's surface
            cpts.set_offsets(np.where(on[:, None], touch, np.nan))
            quiv.set_offsets(touch)
            quiv.set_UVC(NORMAL_LENGTH * n[:, 0], NORMAL_LENGTH * n[:, 1])
        when = f"t = {sc.time[k]:.2f} s" if sc.time_known else f"sample {k}"
        title.set_text(f"{sc.title}\n{when}")
        return []

    anim = animation.FuncAnimation(fig, draw, frames=len(idx), blit=False)
    writer = animation.PillowWriter(fps=fps) if suffix == ".gif" else animation.FFMpegWriter(fps=fps)
    try:
        with atomic_file(path) as tmp:  # the target's suffix: the writers choose the format by it
            anim.save(str(tmp), writer=writer)
    finally:
        plt.close(fig)
    log.info("wrote %s: %d frames", path, len(idx))
    return len(idx)

"""Figure of an evaluation (``tacest eval --plot FILE.png``).

Left: the scene at a few times (true shape solid, estimate dashed, one colour per
time), the finger path and the finger circles where it touched, the ground.  3-D runs
are drawn as their x-z projection (side view).  Right: Chamfer distance, position and
angle error over time.  matplotlib is imported here only, with the Agg backend.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tacest.errors import TacestError
from tacest.geometry.polygon import convex_hull_2d
from tacest.geometry.transforms import transform_points

#: Snapshots of the scene drawn in the left panel.
N_SNAPSHOTS = 6
#: At most this many finger-contact circles (every k-th contact sample), to keep the
#: figure readable on long runs.
MAX_CONTACT_CIRCLES = 80


def _outline(vertices_world, dim):
    """(K, 2) outline in the drawing plane: the shape itself in 2-D, the hull of its
    x-z projection in 3-D."""
    if dim == 2:
        return convex_hull_2d(vertices_world)
    return convex_hull_2d(vertices_world[:, [0, 2]])


def plot_evaluation(path, report: dict, series: dict, est, run, run_index: int = 0,
                    n_snapshots: int = N_SNAPSHOTS) -> None:
    """Draw the evaluation figure to ``path`` (PNG, PDF or SVG by extension).

    report, series: what :func:`tacest.evaluation.metrics.evaluate` returns with
    ``return_series=True``; est: the Estimate; run: the Run with truth.
    Lengths are drawn in mm, angles in degrees.
    """
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle, Polygon

    path = Path(path)
    if not path.parent.is_dir() and str(path.parent):
        raise TacestError(f"{path}: folder {path.parent} does not exist")
    D = run.dim
    T = run.n_samples
    pose_true = np.asarray(run.truth.pose, float)
    pose_est = np.asarray(est.runs[run_index].pose, float)
    Vt = np.asarray(run.truth.vertices, float)
    Ve = np.asarray(est.vertices, float)
    mm = 1e3
    cols = [0, 1] if D == 2 else [0, 2]  # drawing plane: (x, y) in 2-D, (x, z) in 3-D

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(15, 5.6), gridspec_kw={"width_ratios": [1.45, 1.0]})
    cmap = plt.get_cmap("viridis")
    snaps = np.unique(np.linspace(0, T - 1, max(1, int(n_snapshots))).round().astype(int))
    norm = Normalize(vmin=float(run.time[0]), vmax=float(run.time[-1]))

    # finger path and contacts
    pts_for_limits = []
    if run.finger_position is not None:
        fp = np.asarray(run.finger_position, float)[:, :, cols] * mm
        rad = np.asarray(run.finger_radius, float) * mm
        contact = np.asarray(run.contact).astype(bool) if run.contact is not None else np.zeros(fp.shape[:2], bool)
        for f in range(fp.shape[1]):
            ax.plot(fp[:, f, 0], fp[:, f, 1], color="0.55", lw=0.9, zorder=1)
            on = np.flatnonzero(contact[:, f])
            if on.size:
                step = max(1, int(np.ceil(on.size / MAX_CONTACT_CIRCLES)))
                for k in on[::step]:  # every k-th contact sample
                    ax.add_patch(Circle(fp[k, f], rad[f], fill=False, ec="tab:red", lw=0.6, alpha=0.35, zorder=2))
            for k in snaps:
                c = cmap(norm(run.time[k]))
                ax.add_patch(Circle(fp[k, f], rad[f], fc=c if contact[k, f] else "none", ec=c,
                                    alpha=0.45 if contact[k, f] else 0.9, lw=1.2,
                                    ls="-" if contact[k, f] else ":", zorder=5))
        pts_for_limits.append(fp.reshape(-1, 2))

    # shapes at the snapshot times
    for k in snaps:
        c = cmap(norm(run.time[k]))
        wt = _outline(transform_points(pose_true[k], Vt, D), D) * mm
        we = _outline(transform_points(pose_est[k], Ve, D), D) * mm
        ax.add_patch(Polygon(wt, closed=True, fc=c, ec=c, alpha=0.18, lw=0, zorder=3))
        ax.add_patch(Polygon(wt, closed=True, fill=False, ec=c, lw=1.8, zorder=4))
        ax.add_patch(Polygon(we, closed=True, fill=False, ec=c, lw=1.6, ls="--", zorder=4))
        pts_for_limits += [wt, we]

    allp = np.vstack(pts_for_limits)
    lo, hi = allp.min(0), allp.max(0)
    pad = 0.08 * float(np.max(hi - lo)) + 5.0
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ground = float(run.ground_height) * mm
    ax.set_ylim(min(lo[1], ground) - pad, hi[1] + pad)
    # ground: the line n·p = ground_height in the drawing plane
    n = run.up[cols]
    xs = np.array(ax.get_xlim())
    if abs(n[1]) > 1e-9:
        gy = (ground - n[0] * xs) / n[1]
        ax.plot(xs, gy, color="saddlebrown", lw=2, zorder=0)
        ax.fill_between(xs, gy, ax.get_ylim()[0], color="saddlebrown", alpha=0.12, zorder=0)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)" if D == 2 else "z (mm)")
    view = "" if D == 2 else " (side view, x-z projection)"
    ax.set_title(f"True (solid) vs estimated (dashed) shape{view}\n"
                 f"chamfer {report['chamfer'] * mm:.2f} mm, body {report['chamfer_body'] * mm:.2f} mm")
    handles = [Line2D([], [], color="k", lw=1.8, label="true shape"),
               Line2D([], [], color="k", lw=1.6, ls="--", label="estimate"),
               Line2D([], [], color="0.55", lw=0.9, label="finger path"),
               Line2D([], [], color="tab:red", lw=0, marker="o", mfc="none", alpha=0.6, label="finger in contact"),
               Line2D([], [], color="saddlebrown", lw=2, label="ground")]
    ax.legend(handles=handles, loc="best", fontsize=8, framealpha=0.85)
    ax.grid(alpha=0.25)
    cb = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, fraction=0.035, pad=0.02)
    cb.set_label("snapshot time (s)")
    cb.set_ticks(run.time[snaps])
    cb.ax.tick_params(labelsize=8)

    # errors over time
    t = series["time"]
    l1, = ax2.plot(t, series["chamfer"] * mm, color="tab:blue", lw=1.6, label="chamfer (placed)")
    l2, = ax2.plot(t, series["position_error"] * mm, color="tab:orange", lw=1.3, label="COM position error")
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("distance (mm)")
    top = max(float(np.max(series["chamfer"])), float(np.max(series["position_error"]))) * mm
    ax2.set_ylim(0, 1.15 * top if top > 0 else 1.0)
    ax3 = ax2.twinx()
    deg = np.degrees(series["angle_error"])
    l3, = ax3.plot(t, deg, color="tab:green", lw=1.3, ls="--", label="angle error (right axis)")
    ax3.set_ylabel("angle error (deg)")
    ax3.set_ylim(0, 1.15 * float(np.max(deg)) if np.max(deg) > 0 else 1.0)
    for k in snaps:
        ax2.axvline(run.time[k], color="0.85", lw=0.8, zorder=0)
    ax2.legend(handles=[l1, l2, l3], loc="upper left", fontsize=8, framealpha=0.85)
    ax2.grid(alpha=0.25)
    ax2.set_title(f"Errors over time (solver: {report['solver_status']})")
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=130)
    except (OSError, ValueError) as exc:
        raise TacestError(f"{path}: cannot write the figure ({exc})") from None
    finally:
        plt.close(fig)


# ---------------------------------------------------------------------------------
# axis helpers for readable figures (shared by the learning curve and the diagnosis)

#: a panel whose data span less than this fraction of their size gets a fixed range
#: around the value instead of matplotlib's autoscale (which would stretch a 0.002 %
#: wobble over the whole panel, with an offset label)
FLAT_REL_SPAN = 0.01
#: half-width of that fixed range, as a fraction of the value (and at least
#: FLAT_MIN_HALF_WIDTH in the panel's units)
FLAT_HALF_WIDTH = 0.2
FLAT_MIN_HALF_WIDTH = 1.0


def plain_log_axis(ax, axis: str = "y") -> None:
    """Label a log axis (after ``set_yscale("log")``) with plain numbers ("5", "0.2",
    "30") instead of "5×10⁰", on the ticks matplotlib's own formatters would label."""
    from matplotlib.ticker import Formatter

    class _Plain(Formatter):
        def __init__(self, inner):
            self.inner = inner

        def set_axis(self, a):
            super().set_axis(a)
            self.inner.set_axis(a)

        def set_locs(self, locs):
            self.inner.set_locs(locs)

        def __call__(self, v, pos=None):
            return f"{v:g}" if self.inner(v, pos) else ""

    a = ax.yaxis if axis == "y" else ax.xaxis
    a.set_major_formatter(_Plain(a.get_major_formatter()))
    a.set_minor_formatter(_Plain(a.get_minor_formatter()))


def readable_linear_axis(ax, values, axis: str = "y") -> None:
    """No offset/scientific tick labels, and for nearly constant ``values`` (finite
    ones; span below FLAT_REL_SPAN of their size) a fixed range of ± FLAT_HALF_WIDTH of
    the value (at least FLAT_MIN_HALF_WIDTH) around their mean, kept >= 0 for
    non-negative data."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    ax.ticklabel_format(axis=axis, useOffset=False, style="plain")
    if v.size == 0:
        return
    centre, span = float(np.mean(v)), float(np.ptp(v))
    if span > FLAT_REL_SPAN * max(abs(centre), 1e-12):
        return
    half = max(FLAT_HALF_WIDTH * abs(centre), FLAT_MIN_HALF_WIDTH)
    lo, hi = centre - half, centre + half
    if np.all(v >= 0):
        lo = max(lo, 0.0)
    (ax.set_ylim if axis == "y" else ax.set_xlim)(lo, hi)

"""A 3-D scene at a glance as one PNG (matplotlib): the true shape (green edges) and the
estimated one (blue, shaded) at the last sample, every fingertip's path, and the points
the fingers touched (red: the fingertip centre moved back by its radius along the
measured normal, p_contact__world = p_finger__world − r·n̂).  Two views side by side:
an oblique one and the view from above.  The animated, rotatable counterpart is
tacest.view.html3d.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from tacest.errors import TacestError
from tacest.io.outputs import atomic_file
from tacest.view.scene import Scene

log = logging.getLogger(__name__)

#: (elevation, azimuth) deg of the two views: oblique, and from above
VIEWS = ((25.0, -60.0), (89.0, -90.0))


def _placed_mesh(vertices__body, pose):
    """(vertices (K, 3) m world frame, triangles (n, 3), feature edges (e, 2)) of the
    convex hull of ``vertices__body`` placed at ``pose`` [x, y, z, qw, qx, qy, qz]."""
    from tacest.geometry.polytope import convex_hull_mesh
    from tacest.geometry.transforms import quat_to_matrix
    from tacest.view.html3d import FEATURE_ANGLE

    mesh = convex_hull_mesh(vertices__body)
    pose = np.asarray(pose, float)
    q = pose[3:] / np.linalg.norm(pose[3:])
    V = np.asarray(mesh.vertices, float) @ quat_to_matrix(q).T + pose[:3]
    edges = mesh.face_adjacency_edges[mesh.face_adjacency_angles > FEATURE_ANGLE]
    return V, np.asarray(mesh.faces), np.asarray(edges)


def touched_points(sc: Scene) -> np.ndarray:
    """(n, 3) m, world frame: the contact points of every sample and finger in contact."""
    if sc.finger_position is None or sc.contact is None or sc.normal is None:
        return np.zeros((0, 3))
    on = np.asarray(sc.contact, bool) & np.all(np.isfinite(sc.normal), axis=-1)
    r = np.broadcast_to(np.asarray(sc.finger_radius, float)[None, :, None], sc.finger_position.shape)
    p = sc.finger_position - r * np.nan_to_num(sc.normal)
    return p[on]


def write_png_3d(sc: Scene, path, title: str | None = None) -> None:
    """Write the PNG view of the 3-D scene ``sc`` (module docstring) to ``path``."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    path = Path(path)
    if sc.dim != 3:
        raise TacestError(f"{path}: a 3-D view needs a 3-D scene, got {sc.dim}-D")
    fig = plt.figure(figsize=(10, 4.8))
    pts = [np.zeros((0, 3))]
    touched = touched_points(sc)
    for i, (elev, azim) in enumerate(VIEWS):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        if sc.est_vertices is not None and sc.est_pose is not None:
            V, tri, _ = _placed_mesh(sc.est_vertices, sc.est_pose[-1])
            ax.add_collection3d(Poly3DCollection(V[tri], facecolor=(0.3, 0.5, 0.9, 0.35),
                                                 edgecolor=(0.2, 0.3, 0.7, 0.5), linewidths=0.3, label="estimate"))
            pts.append(V)
        if sc.true_vertices is not None and sc.true_pose is not None:
            V, _, edges = _placed_mesh(sc.true_vertices, sc.true_pose[-1])
            ax.add_collection3d(Line3DCollection(V[edges], colors="green", linewidths=1.2, label="truth"))
            pts.append(V)
        if sc.finger_position is not None:
            for f in range(sc.finger_position.shape[1]):
                p = sc.finger_position[:, f]
                ax.plot(p[:, 0], p[:, 1], p[:, 2], lw=0.8, alpha=0.7, label=f"finger {f}")
        if len(touched):
            ax.scatter(touched[:, 0], touched[:, 1], touched[:, 2], s=3, c="red", depthshade=False,
                       label="touched")
        allp = np.concatenate(pts + [touched])
        if len(allp):
            c = 0.5 * (allp.min(0) + allp.max(0))
            h = 0.55 * float(np.max(allp.max(0) - allp.min(0))) + 1e-3
            ax.set_xlim(c[0] - h, c[0] + h)
            ax.set_ylim(c[1] - h, c[1] + h)
            ax.set_zlim(max(0.0, c[2] - h), max(0.0, c[2] - h) + 2 * h)
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x (m)", fontsize=7)
        ax.set_ylabel("y (m)", fontsize=7)
        if elev < 80:
            ax.set_zlabel("z (m)", fontsize=7)
        else:  # seen from above, the height axis is a smear of labels
            ax.set_zticks([])
        ax.tick_params(labelsize=6)
        if i == 0:
            ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(title or sc.title, fontsize=9)
    fig.tight_layout()
    try:
        with atomic_file(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
    finally:
        plt.close(fig)
    log.info("wrote %s", path)

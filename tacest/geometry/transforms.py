"""Rigid transforms in numpy: 2-D rotations, unit quaternions and pose vectors.

Conventions (SPEC v1):

- quaternions are scalar first, ``q = [qw, qx, qy, qz]``, unit length;
- a pose maps body to world: ``p__world = R(pose) @ p__body + t(pose)``;
- pose vectors are ``[x, y, angle]`` in 2-D (angle in rad, counter-clockwise) and
  ``[x, y, z, qw, qx, qy, qz]`` in 3-D.

Every function accepts stacked inputs with any leading shape ``(...)``; the last axis
holds the vector.  These are plain numpy; the estimator has its own CasADi versions.
"""

from __future__ import annotations

import numpy as np

from tacest.errors import TacestError

#: Quaternions with norm below this cannot be normalised (they carry no rotation).
_QUAT_MIN_NORM = 1e-12


# ---------------------------------------------------------------------------------
# angles and 2-D rotations


def wrap_angle(angle):
    """Wrap angles (rad) to [-pi, pi).  Shape preserved."""
    a = np.asarray(angle, float)
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def rot2(angle) -> np.ndarray:
    """2-D rotation matrices.

    angle : (...) float, rad, counter-clockwise.
    Returns (..., 2, 2) with ``R @ [1, 0] = [cos, sin]``.
    """
    a = np.asarray(angle, float)
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def angle_of_rot2(R) -> np.ndarray:
    """Angle (rad, in (-pi, pi]) of 2-D rotation matrices ``R`` (..., 2, 2)."""
    R = np.asarray(R, float)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


# ---------------------------------------------------------------------------------
# quaternions (scalar first)


def quat_normalize(q) -> np.ndarray:
    """Unit quaternions (..., 4); raises TacestError for a (near) zero quaternion."""
    q = np.asarray(q, float)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < _QUAT_MIN_NORM):
        raise TacestError("cannot normalise a zero quaternion")
    return q / n


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` (..., 4): rotating by ``b`` first, then by ``a``."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def quat_conjugate(q) -> np.ndarray:
    """Conjugate ``[w, -x, -y, -z]`` (the inverse of a unit quaternion), (..., 4)."""
    q = np.asarray(q, float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) (normalised first)."""
    w, x, y, z = np.moveaxis(quat_normalize(q), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def quat_from_matrix(R) -> np.ndarray:
    """Unit quaternions (..., 4) with ``qw >= 0`` from rotation matrices (..., 3, 3).

    Uses scipy's robust (Shepperd-type) conversion; the input is projected onto
    SO(3) implicitly, so slightly non-orthogonal matrices are fine.
    """
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, float)
    lead = R.shape[:-2]
    xyzw = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q = np.concatenate([xyzw[:, 3:4], xyzw[:, :3]], axis=1)
    q = np.where(q[:, :1] < 0, -q, q)
    return q.reshape(lead + (4,))


def quat_rotate(q, v) -> np.ndarray:
    """Rotate vectors ``v`` (..., 3) by quaternions ``q`` (..., 4); broadcasting."""
    R = quat_to_matrix(q)
    return np.einsum("...ij,...j->...i", R, np.asarray(v, float))


def quat_angle(a, b) -> np.ndarray:
    """Geodesic angle (rad, in [0, pi]) between the rotations of quaternions a and b.

    ``2 * atan2(|vec(a* ⊗ b)|, |scalar(a* ⊗ b)|)``: exact near 0 (unlike
    ``2 acos(|<a, b>|)``) and the same for ``q`` and ``-q``.
    """
    d = quat_multiply(quat_conjugate(quat_normalize(a)), quat_normalize(b))
    return 2.0 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0]))


def quat_from_axis_angle(axis, angle) -> np.ndarray:
    """Quaternion (..., 4) of a rotation by ``angle`` (rad) about unit ``axis`` (..., 3)."""
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    half = 0.5 * np.asarray(angle, float)[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * axis], -1)


def quat_from_rotvec(phi) -> np.ndarray:
    """Quaternions (..., 4) of rotation vectors phi (..., 3) rad (axis times angle;
    the identity at phi = 0)."""
    phi = np.asarray(phi, float)
    a = np.linalg.norm(phi, axis=-1, keepdims=True)
    s = np.where(a > 1e-12, np.sin(a / 2) / np.maximum(a, 1e-12), 0.5)
    return np.concatenate([np.cos(a / 2), s * phi], -1)


# ---------------------------------------------------------------------------------
# poses


def pose_size(dim: int) -> int:
    """3 in 2-D, 7 in 3-D."""
    return 3 if dim == 2 else 7


def pose_rotation(pose, dim: int) -> np.ndarray:
    """Rotation matrices (..., D, D) of pose vectors (..., P), body to world."""
    pose = np.asarray(pose, float)
    return rot2(pose[..., 2]) if dim == 2 else quat_to_matrix(pose[..., 3:7])


def transform_points(pose, points, dim: int) -> np.ndarray:
    """Body-frame points to world frame.

    pose : (..., P) pose vectors; points : (N, D) body frame, m.
    Returns (..., N, D) world frame, m: ``R(pose) @ p + t(pose)``.
    """
    pose = np.asarray(pose, float)
    R = pose_rotation(pose, dim)
    t = pose[..., :dim]
    return np.einsum("...ij,nj->...ni", R, np.asarray(points, float)) + t[..., None, :]


def relative_transform(pose_from, pose_to, dim: int):
    """The rigid map taking body-``from`` coordinates to body-``to`` coordinates.

    For a point with body coordinates ``p`` under ``pose_from``, its coordinates in
    the body frame of ``pose_to`` are ``R @ p + t`` with
    ``R = R_to^T R_from``, ``t = R_to^T (t_from - t_to)``.

    Returns R (..., D, D), t (..., D).
    """
    pf = np.asarray(pose_from, float)
    pt = np.asarray(pose_to, float)
    Rf, Rt = pose_rotation(pf, dim), pose_rotation(pt, dim)
    RtT = np.swapaxes(Rt, -1, -2)
    R = RtT @ Rf
    t = np.einsum("...ij,...j->...i", RtT, pf[..., :dim] - pt[..., :dim])
    return R, t


def pose_angle_error(pose_a, pose_b, dim: int) -> np.ndarray:
    """Rotation angle (rad, >= 0) between the orientations of two poses, (...).

    2-D: ``|wrap(angle_a - angle_b)|``; 3-D: the geodesic quaternion angle.
    """
    a = np.asarray(pose_a, float)
    b = np.asarray(pose_b, float)
    if dim == 2:
        return np.abs(wrap_angle(a[..., 2] - b[..., 2]))
    return quat_angle(a[..., 3:7], b[..., 3:7])


def project_to_rotation(M) -> np.ndarray:
    """Nearest proper rotation (Frobenius norm) to a square matrix (D, D), via SVD."""
    U, _, Vt = np.linalg.svd(np.asarray(M, float))
    S = np.eye(U.shape[0])
    S[-1, -1] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ S @ Vt


def cube_rotations() -> np.ndarray:
    """The 24 proper rotations of the cube, (24, 3, 3): signed permutation matrices
    with determinant +1.  The identity comes first; order is deterministic."""
    import itertools

    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            for i, (j, s) in enumerate(zip(perm, signs)):
                M[i, j] = s
            if np.linalg.det(M) > 0:
                out.append(M)
    return np.array(out)


def so3_grid(n: int) -> np.ndarray:
    """n rotations (n, 3, 3) spread nearly uniformly over SO(3), deterministic:
    the super-Fibonacci spiral of Alexa (CVPR 2022).  For n = 256 every rotation is
    within ~20° of a grid rotation."""
    n = int(n)
    phi = np.sqrt(2.0)
    psi = 1.533751168755204288118041
    s = np.arange(n) + 0.5
    r = np.sqrt(s / n)
    R = np.sqrt(1.0 - s / n)
    alpha = 2.0 * np.pi * s / phi
    beta = 2.0 * np.pi * s / psi
    q = np.stack([r * np.sin(alpha), r * np.cos(alpha), R * np.sin(beta), R * np.cos(beta)], 1)
    return quat_to_matrix(q)

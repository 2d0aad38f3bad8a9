"""The 2-D forward model of many object hypotheses (tacest.model.forward2d), the sampler's
simulator: statics, free flight, the measured-force drive, the fingertip's signed distance
and its gradient, substepping and invariance under a rigid motion of the whole world."""

from __future__ import annotations

import numpy as np
import pytest

from tacest.model.forward2d import GROUND_SINK, Hypotheses, World2D, box_hypotheses, finger_geometry

W, H = 0.10, 0.16  # m, the test box
G = 9.81


def _boxes(n, mass=0.3, mu_g=0.5, mu_f=0.3):
    return box_hypotheses(np.full(n, W), np.full(n, H), np.full(n, mass), np.full(n, mu_g), np.full(n, mu_f))


def _rot(a):
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def _box_sd(p):
    """Signed distance (N,) of body-frame points (N, 2) to the W x H box (the textbook
    formula: outside the norm of the positive excess, inside the largest excess)."""
    q = np.abs(p) - [W / 2, H / 2]
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def test_a_tilted_box_settles_back_or_topples_by_its_balance_angle():
    """Known answer of rigid-body statics: a box tilted by less than its balance angle
    atan(W / H) (0.56 rad) falls back onto its bottom face, by more it topples onto its
    side; at rest the centre is half the supporting extent above the ground less the
    penalty spring's sink (GROUND_SINK, 1 mm: tolerance 0.2 mm), and nothing moves."""
    world = World2D([0, 1], 0.0, [0, -G], [0.01])
    tilt = np.array([0.0, 0.3, 0.5, 0.62, 1.0])
    hyp = _boxes(len(tilt))
    pose = world.rest_pose(hyp.vertices, np.zeros(len(tilt)), tilt)
    vel = np.zeros_like(pose)
    for _ in range(3):
        pose, vel, _ = world.advance(hyp, pose, vel, 1e-3, 1000)
    toppled = tilt > np.arctan2(W, H)
    np.testing.assert_allclose(pose[:, 1], np.where(toppled, W / 2, H / 2) - GROUND_SINK, atol=2e-4)
    turned = np.abs(np.sin(pose[:, 2]))  # 0 on the bottom face, 1 on a side
    np.testing.assert_allclose(turned, toppled.astype(float), atol=1e-3)
    assert np.abs(vel).max() < 1e-6


def test_free_flight_is_ballistic_and_a_measured_force_accelerates_it_exactly():
    """Far above the ground, semi-implicit Euler integrates a constant acceleration
    exactly in velocity: after n steps of h, v = v0 + n h (F / m + g) and
    omega = omega0 + h (r x F) / I over one step (to rounding, 1e-12), and the position
    is the parabola plus semi-implicit Euler's known a·h·t/2."""
    world = World2D([0, 1], 0.0, [0, -G], [0.01])
    hyp = _boxes(2, mass=np.array([0.2, 0.5]))
    pose = np.array([[0.0, 1.0, 0.3], [0.1, 1.2, -0.4]])
    v0 = np.array([[0.3, 1.0, 2.0], [-0.2, 0.5, -1.0]])
    F, point = np.array([0.4, -0.1]), np.array([0.02, 1.1])
    h, n = 1e-3, 300
    p1, v1, _ = world.advance(hyp, pose, v0, h, n, forces=[(point, F)])
    m, I = hyp.mass, hyp.inertia
    # the force's lever changes as the body moves: the linear part is exact; without a
    # force the spin is constant
    np.testing.assert_allclose(v1[:, :2], v0[:, :2] + n * h * (F[None] / m[:, None] + [0, -G]), rtol=0, atol=1e-12)
    _, v2, _ = world.advance(hyp, pose, v0, h, n)
    np.testing.assert_allclose(v2[:, 2], v0[:, 2], rtol=0, atol=1e-12)
    # one step: the torque of the force at its lever from the starting pose
    _, v3, _ = world.advance(hyp, pose, v0, h, 1, forces=[(point, F)])
    r = point[None] - pose[:, :2]
    np.testing.assert_allclose(v3[:, 2], v0[:, 2] + h * (r[:, 0] * F[1] - r[:, 1] * F[0]) / I, rtol=0, atol=1e-12)
    # semi-implicit Euler's position: the parabola plus a h t / 2 (sum of k h² a, k = 1..n)
    t = n * h
    expect = pose[:, :2] + v0[:, :2] * t + 0.5 * (F[None] / m[:, None] + [0, -G]) * t * (t + h)
    np.testing.assert_allclose(p1[:, :2], expect, rtol=0, atol=1e-12)


def _polygon(n):
    """(1, n, 2) a regular polygon of circumradius 0.06 m, CCW, COM at the origin."""
    a = 2 * np.pi * np.arange(n) / n + 0.1
    return 0.06 * np.stack([np.cos(a), np.sin(a)], -1)[None]


def test_the_finger_geometry_is_the_signed_distance_and_its_gradient():
    """finger_geometry against the box's textbook signed distance on random points (in
    and out) and, for a box and a pentagon, its normal against central differences of the
    distance (h 1e-6 m; tolerance 1e-6 where the closest feature does not change inside
    the step), the point sd along the normal from the returned surface point."""
    rng = np.random.default_rng(0)
    n = 300
    pose = np.stack([rng.normal(0, 0.02, n), rng.normal(0, 0.02, n), rng.uniform(-3, 3, n)], 1)
    pts = pose[:, :2] + rng.normal(0, 0.07, size=(n, 2))
    hyp = _boxes(n)
    sd, n_w, point = np.zeros(n), np.zeros((n, 2)), np.zeros((n, 2))
    for i in range(n):
        a, b, c = finger_geometry(hyp.take([i]), pose[i:i + 1], pts[i])
        sd[i], n_w[i], point[i] = a[0], b[0], c[0]
    body = np.einsum("nji,nj->ni", np.stack([_rot(a) for a in pose[:, 2]]), pts - pose[:, :2])
    np.testing.assert_allclose(sd, _box_sd(body), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(n_w, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(point + sd[:, None] * n_w, pts, atol=1e-12)
    for V in (hyp.vertices[:1], _polygon(5)):
        one = Hypotheses(V, np.ones(1), np.ones(1), np.ones(1), np.ones(1))
        P = pose[:1]
        for q in pts[:60]:
            s0, nrm, _ = finger_geometry(one, P, q)
            grad = np.array([(finger_geometry(one, P, q + e)[0] - finger_geometry(one, P, q - e)[0])[0] / 2e-6
                             for e in (np.array([1e-6, 0.0]), np.array([0.0, 1e-6]))])
            np.testing.assert_allclose(grad, nrm[0], atol=1e-6)


def _pushed(world, hyp, pose, c0, c1, v, n_sub):
    return world.advance(hyp, pose, np.zeros_like(pose), 1e-3, n_sub, fingers=[(1, c1, v)], start_centres=[c0])


def test_advance_is_its_substeps_one_by_one():
    """World2D.advance with n_sub substeps is n_sub calls of one substep with the fingertip
    interpolated linearly from its start to its end centre (to rounding); the returned
    force is the substeps' mean; a fingertip at NaN pushes nothing; sizes are checked."""
    world = World2D([0, 1], 0.0, [0, -G], [0.01, 0.012])
    n = 5
    hyp = box_hypotheses(np.linspace(0.8, 1.2, n) * W, np.full(n, H), np.linspace(0.1, 0.5, n), np.full(n, 0.6),
                         np.full(n, 0.3))
    pose = world.rest_pose(hyp.vertices, np.zeros(n), np.full(n, 0.1))
    c0, c1, v = np.array([-0.058, 0.05]), np.array([-0.054, 0.05]), np.array([0.4, 0.0])
    a_pose, a_vel, F_a = _pushed(world, hyp, pose, c0, c1, v, 10)
    b_pose, b_vel, F_sum = pose, np.zeros_like(pose), 0.0
    for j in range(10):
        cj = c0 + (j + 1) / 10 * (c1 - c0)
        b_pose, b_vel, F_b = world.advance(hyp, b_pose, b_vel, 1e-3, 1, fingers=[(1, cj, v)])
        F_sum = F_sum + F_b / 10
    np.testing.assert_allclose(a_pose, b_pose, rtol=0, atol=1e-15)
    np.testing.assert_allclose(a_vel, b_vel, rtol=0, atol=1e-12)
    np.testing.assert_allclose(F_a, F_sum, rtol=0, atol=1e-12)
    assert np.abs(F_a).max() > 0.1  # the finger pushed
    assert np.abs(a_pose - pose).max() > 1e-5  # and the boxes moved
    c_pose, c_vel, F_c = _pushed(world, hyp, pose, c0, np.full(2, np.nan), v, 10)
    assert np.all(F_c == 0.0) and np.isfinite(c_pose).all() and np.isfinite(c_vel).all()
    with pytest.raises(ValueError, match="hypotheses"):
        world.advance(hyp, pose[:2], np.zeros((2, 3)), 1e-3, 10)


def test_a_rigid_motion_of_the_whole_world_moves_the_result_with_it():
    """Invariance: turning the ground, gravity, the object's pose and the fingertip's
    path by the same angle and shifting them by the same vector gives the same motion,
    turned and shifted (to 1e-9 m, 1e-9 rad: rounding through 300 stiff steps)."""
    n = 4
    hyp = box_hypotheses(np.linspace(0.08, 0.12, n), np.full(n, H), np.full(n, 0.3), np.full(n, 0.5),
                         np.full(n, 0.4))
    c0, c1, v = np.array([-0.075, 0.05]), np.array([-0.07, 0.05]), np.array([0.5, 0.0])

    def run(alpha, shift):
        R = _rot(alpha)
        up = R @ [0.0, 1.0]
        world = World2D(up, float(up @ shift), R @ [0.0, -G], [0.01, 0.012])
        pose = world.rest_pose(hyp.vertices, np.full(n, float(shift @ (R @ [1.0, 0.0]))), np.full(n, alpha))
        vel = np.zeros_like(pose)
        for k in range(30):
            a, b = c0 + k / 30 * (c1 - c0), c0 + (k + 1) / 30 * (c1 - c0)
            pose, vel, _ = world.advance(hyp, pose, vel, 1e-3, 10, fingers=[(1, R @ b + shift, R @ v)],
                                         start_centres=[R @ a + shift])
        return pose, vel

    ref_pose, ref_vel = run(0.0, np.zeros(2))
    alpha, shift = 0.7, np.array([0.3, -0.2])
    pose, vel = run(alpha, shift)
    R = _rot(alpha)
    np.testing.assert_allclose(pose[:, :2], ref_pose[:, :2] @ R.T + shift, atol=1e-9)
    np.testing.assert_allclose(pose[:, 2], ref_pose[:, 2] + alpha, atol=1e-9)
    np.testing.assert_allclose(vel[:, :2], ref_vel[:, :2] @ R.T, atol=1e-7)
    np.testing.assert_allclose(vel[:, 2], ref_vel[:, 2], atol=1e-7)
    assert np.abs(ref_pose[:, 0]).max() > 1e-4  # the boxes were pushed

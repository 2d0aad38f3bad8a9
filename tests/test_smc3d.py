"""The 3-D forward model of many box hypotheses (tacest.model.forward3d) and the sampling
start of the 3-D estimator (tacest.estimation.smc3d) on a box that topples."""

from __future__ import annotations

import numpy as np
import pytest

from tacest.estimation.initial3d import _box_signed_distance
from tacest.geometry.transforms import quat_from_rotvec, quat_multiply, quat_to_matrix
from tacest.model.forward3d import GROUND_SINK, Boxes, World3D, box_finger_geometry
from tests.test_dynamic import TOPPLE_3D

HALF = np.array([0.05, 0.04, 0.06])  # m
G = 9.81


def _boxes(n, mass=0.3, mu_g=0.5):
    return Boxes(np.repeat(HALF[None], n, 0), np.full(n, mass), np.full(n, mu_g), np.full(n, 0.3))


def _settle(world, hyp, quat, steps=2500, h=1e-3):
    n = len(hyp.mass)
    pos = world.rest_position(hyp.half, quat_to_matrix(quat), np.zeros((n, 3)))
    vel, om = np.zeros((n, 3)), np.zeros((n, 3))
    for _ in range(steps):
        pos, quat, vel, om, _ = world.step(hyp, pos, quat, vel, om, h)
    return pos, quat, vel, om


def test_a_tilted_box_settles_back_or_topples_by_its_balance_angle():
    """Known answer of rigid-body statics: a box tilted about y by less than its balance
    angle atan(a_x / a_z) (0.69 rad here) falls back onto its face, by more it topples
    onto the x face; at rest the centre is the supporting half extent above the ground,
    less the penalty spring's sink (GROUND_SINK, 1 mm: the tolerance), and nothing moves."""
    world = World3D([0, 0, 1], 0.0, [0, 0, -G], [0.01])
    tilt = np.array([0.0, 0.3, 0.6, 0.8, 1.2])
    quat = quat_from_rotvec(np.stack([0 * tilt, tilt, 0 * tilt], 1))
    pos, quat, vel, om = _settle(world, _boxes(len(tilt)), quat)
    up_axis = np.abs(quat_to_matrix(quat)[:, 2, :])  # |world z of the body axes|
    toppled = tilt > np.arctan2(HALF[0], HALF[2])
    np.testing.assert_allclose(pos[:, 2], np.where(toppled, HALF[0], HALF[2]) - GROUND_SINK, atol=2e-4)
    np.testing.assert_allclose(up_axis[:, 0], toppled.astype(float), atol=1e-3)
    assert np.abs(vel).max() < 1e-6 and np.abs(om).max() < 1e-5


def test_free_flight_is_ballistic_and_keeps_its_angular_momentum():
    """Far above the ground: the COM follows the parabola (semi-implicit Euler: error
    h·v_z-type, below 0.2 mm over 0.3 s at h = 1 ms) and a torque-free spin keeps
    |L| (explicit Euler on the body rates: growth ~ h·|ω|² relative, below 1 %)."""
    world = World3D([0, 0, 1], 0.0, [0, 0, -G], [0.01])
    hyp = _boxes(1)
    pos, quat = np.array([[0.0, 0.0, 1.0]]), quat_from_rotvec(np.array([[0.2, -0.1, 0.3]]))
    v0, om = np.array([[0.3, -0.2, 1.0]]), np.array([[2.0, 5.0, -1.0]])
    vel = v0.copy()
    L0 = np.linalg.norm(quat_to_matrix(quat)[0] @ (hyp.inertia[0] * om[0]))
    h, n = 1e-3, 300
    for _ in range(n):
        pos, quat, vel, om, _ = world.step(hyp, pos, quat, vel, om, h)
    t = n * h
    expect = np.array([0.0, 0.0, 1.0]) + v0[0] * t + 0.5 * np.array([0, 0, -G]) * t * t
    np.testing.assert_allclose(pos[0], expect, atol=2e-3)
    L1 = np.linalg.norm(quat_to_matrix(quat)[0] @ (hyp.inertia[0] * om[0]))
    assert abs(L1 / L0 - 1) < 0.01


def test_advance_is_its_substeps_one_by_one():
    """World3D.advance (the compiled kernel, every substep of a sample in one call) is
    n_sub calls of step with the fingertip interpolated linearly from its start to its
    end centre and the measured forces held, bit for bit (the same kernel)."""
    world = World3D([0, 0, 1], 0.0, [0, 0, -G], [0.01, 0.012])
    n = 5
    hyp = Boxes(HALF[None] * np.linspace(0.8, 1.2, n)[:, None], np.linspace(0.1, 0.5, n), np.full(n, 0.6),
                np.full(n, 0.3))
    quat = quat_from_rotvec(np.tile([0.0, 0.2, 0.0], (n, 1)))
    pos = world.rest_position(hyp.half, quat_to_matrix(quat), np.zeros((n, 3)))
    state = (pos, quat, np.zeros((n, 3)), np.zeros((n, 3)))
    c0, c1, v = np.array([-0.07, 0.0, 0.05]), np.array([-0.066, 0.0, 0.05]), np.array([0.4, 0.0, 0.0])
    force = [(np.array([0.0, 0.02, 0.08]), np.array([0.0, -0.2, 0.0]))]
    *a, F_a = world.advance(hyp, *state, 1e-3, 10, fingers=[(1, c1, v)], start_centres=[c0], forces=force)
    b = state
    for j in range(10):
        *b, F_b = world.step(hyp, *b, 1e-3, fingers=[(1, c0 + (j + 1) / 10 * (c1 - c0), v)], forces=force)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-15)
    np.testing.assert_allclose(F_a[:, 0], F_b[0], rtol=0, atol=1e-12)
    assert np.abs(F_a).max() > 0.1  # the finger pushed
    assert np.abs(a[0] - pos).max() > 1e-5  # and the boxes moved
    # a fingertip at NaN (lost tracking) pushes nothing, as the numpy model did
    *c, F_c = world.advance(hyp, *state, 1e-3, 10, fingers=[(1, np.full(3, np.nan), v)], start_centres=[c0])
    assert np.all(F_c == 0.0) and all(np.isfinite(x).all() for x in c)
    with pytest.raises(ValueError, match="other sizes"):
        world.advance(hyp, pos[:2], *state[1:], 1e-3, 10)


def test_the_finger_geometry_is_the_box_signed_distance_and_its_gradient():
    """box_finger_geometry against initial3d's signed distance on random points (in and
    out) and its normal against central differences (h 1e-6 m; where the closest
    feature does not change inside the step)."""
    rng = np.random.default_rng(0)
    n = 200
    half = np.repeat(HALF[None], n, 0)
    R = quat_to_matrix(quat_from_rotvec(rng.normal(0, 1, size=(n, 3))))
    pos = rng.normal(0, 0.02, size=(n, 3))
    pts = pos + rng.normal(0, 0.06, size=(n, 3))
    sd, n_w, point = np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3))
    for i in range(n):
        a, b, c = box_finger_geometry(half[i:i + 1], R[i:i + 1], pos[i:i + 1], pts[i])
        sd[i], n_w[i], point[i] = a[0], b[0], c[0]
    body = np.einsum("nji,nj->ni", R, pts - pos)
    np.testing.assert_allclose(sd, _box_signed_distance(body, half), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(n_w, axis=1), 1.0, atol=1e-12)
    # the surface point is on the surface, and the query point is sd along the normal from it
    np.testing.assert_allclose(_box_signed_distance(np.einsum("nji,nj->ni", R, point - pos), half), 0.0, atol=1e-12)
    np.testing.assert_allclose(point + sd[:, None] * n_w, pts, atol=1e-12)
    hstep = 1e-6
    grad = np.zeros((n, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = hstep
        up = _box_signed_distance(np.einsum("nji,nj->ni", R, pts + e - pos), half)
        dn = _box_signed_distance(np.einsum("nji,nj->ni", R, pts - e - pos), half)
        grad[:, k] = (up - dn) / (2 * hstep)
    np.testing.assert_allclose(grad, n_w, atol=1e-6)


def test_a_turn_about_the_vertical_is_no_tilt():
    """The sampler's tilt (which decides whether its start goes first) is the angle of the
    ground normal in the body frame: 40 degrees of yaw give 0, 30 degrees about x give 30
    whatever the yaw."""
    from types import SimpleNamespace

    from tacest.estimation.smc3d import _max_tilt_deg

    run = SimpleNamespace(up=np.array([0.0, 0.0, 1.0]))
    yaw = np.linspace(0, np.radians(40), 50)
    spin = np.concatenate([np.zeros((50, 3)), quat_from_rotvec(np.stack([0 * yaw, 0 * yaw, yaw], 1))], 1)
    assert _max_tilt_deg([run], [spin]) == pytest.approx(0.0, abs=1e-6)
    tip = spin.copy()
    tilt = np.linspace(0, np.radians(30), 50)
    tip[:, 3:] = quat_multiply(spin[:, 3:], quat_from_rotvec(np.stack([tilt, 0 * tilt, 0 * tilt], 1)))  # Rz Rx
    assert _max_tilt_deg([run], [tip]) == pytest.approx(30.0, abs=1e-6)


@pytest.fixture(scope="module")
def toppled_no_force():
    """tests/test_dynamic.py's 3-D topple (96 degrees), contact and normal only, noiseless."""
    from tacest.dims import record_sim
    from tacest.sim.record import SimOptions

    return record_sim(SimOptions(noise_force=0.0, noise_position=0.0, noise_normal=0.0, force_stream=False,
                                 **TOPPLE_3D))


def test_the_3d_sampling_start_is_reproducible_from_its_seed(toppled_no_force):
    from tacest.estimation.smc3d import SMC3DSettings, smc_start_3d

    run = toppled_no_force
    a, b, c = (smc_start_3d([run], 0.1, 0.5, np.full(3, 0.1), SMC3DSettings(particles=32, seed=s)) for s in (4, 4, 5))
    np.testing.assert_array_equal(a.extents, b.extents)
    np.testing.assert_array_equal(a.poses[0], b.poses[0])
    assert a.log_likelihood == b.log_likelihood
    assert not np.array_equal(a.extents, c.extents)


@pytest.mark.slow
def test_contact_and_normal_alone_follow_a_3d_topple(toppled_no_force):
    """Tactile-only known answer in 3-D: three fingertips, contact flags and normals, no
    force, no pose; the box topples 96 degrees.  Estimated with the growing horizon
    (solver3d.growing_horizon): the first poke's estimate is the first start, the
    sampler's lineage tips (so it goes before the push-tracked starts), and the estimate
    places the box within 5 mm (Chamfer of the placed shapes: 3.5 mm seen, body 2.0 mm)
    and says it is consistent.  Tolerances:
    the pokes touch the y faces only at the edge the finger rides over, so that extent
    is loosely held (120 mm for 109 seen); the mass is not identifiable without force.
    Before the sampler the same run gave no fit from any of 3 starts."""
    from tacest.dims import estimate_runs
    from tacest.estimation.config import EstimatorConfig
    from tacest.evaluation.metrics import evaluate

    run = toppled_no_force
    est = estimate_runs([run], "box", config=EstimatorConfig().updated({"solver3d": {"growing_horizon": True}}))
    rep = evaluate(est, run, 0)
    import json

    starts = json.loads(est.extra_attrs["starts"])
    assert [a["start"] for a in starts[:2]] == ["previous estimate", "sampler"], starts
    assert starts[1]["max_tilt_deg"] > 60.0, starts[1]
    horizon = json.loads(est.extra_attrs["horizon"])  # one step: the first poke alone
    assert len(horizon) == 1 and horizon[0]["samples"] < run.n_samples, horizon
    assert rep["chamfer"] < 5e-3 and rep["chamfer_body"] < 3e-3, (rep["chamfer"], rep["chamfer_body"])
    assert est.consistent is True, est.fit_quality
    assert rep["chamfer_body"] <= 3.0 * est.std["shape"]


def test_a_polytope_estimate_gets_the_sampled_start_too(toppled_no_force, monkeypatch):
    """The sampler's hypotheses are boxes; a polytope:K estimate is offered its lineage
    too (it had the push-tracked starts alone, which never tip), started as the
    polytope of the lineage's box extents on the lineage's tipping poses."""
    monkeypatch.setenv("TACEST_NO_COMPILE", "1")
    from tacest.estimation.estimator3d import Estimator3D
    from tacest.estimation.initial3d import start_candidates_3d

    est = Estimator3D([toppled_no_force], "polytope:8")  # the default sampler: 8 runs of 256, one start
    tracked = start_candidates_3d(est.runs, est.scales.L, np.ones(3), 1)[0]
    (sampled,) = est.sampled_starts(tracked)
    assert sampled.label == "sampler"
    assert sampled.extra["max_tilt_deg"] > 30.0
    assert sampled.shape_params is None  # solved from est.shape.initial(extents): the polytope of the box
    assert len(est.shape.initial(sampled.extents)) == 8


def test_the_growing_horizon_applies_to_one_poked_run_of_several_actions_only(toppled_no_force):
    """grow_horizon returns (None, []) without solving anything for two runs, for a run
    with pose observations, and for a run of one action (there is nothing to grow)."""
    from tacest.io.slicing import action_ranges, slice_run
    from tacest.estimation.config import EstimatorConfig
    from tacest.estimation.estimator3d import grow_horizon

    run = toppled_no_force
    cfg = EstimatorConfig()
    assert len(action_ranges(run)) == 2
    assert grow_horizon([run, run], "box", cfg) == (None, [])
    observed = run.replace(pose_obs=np.asarray(run.truth.pose, float).copy())
    assert grow_horizon([observed], "box", cfg) == (None, [])
    first = slice_run(run, 0, action_ranges(run)[0][1])
    assert grow_horizon([first], "box", cfg) == (None, [])

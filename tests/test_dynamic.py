"""Dynamic pokes: the sampling start (tacest.estimation.smc2d) and the estimator on an
object that topples (2-D)."""

from __future__ import annotations

import numpy as np
import pytest

from tacest.sim.record import SimOptions, record_sim

#: a high poke that topples the box over one edge (90 degrees) in 2.6 s, seed 8 of
#: SimOptions(poke_style="high", pokes=2): found by scanning seeds 0-11 (seeds 8, 10
#: and 11 topple; most high pokes of two only tip it or slide it)
TOPPLE = dict(object_spec="box", pokes=2, seed=8, poke_style="high")


def _max_tilt_deg(run) -> float:
    a = np.unwrap(run.truth.pose[:, 2])
    return float(np.degrees(np.max(np.abs(a - a[0]))))


@pytest.fixture(scope="module")
def toppled():
    """The toppling recording without sensor noise."""
    run = record_sim(SimOptions(noise_force=0.0, noise_position=0.0, noise_normal=0.0, **TOPPLE))
    assert _max_tilt_deg(run) > 80.0  # the recording does what the test is about
    return run


def test_the_sampling_start_is_reproducible_from_its_seed(toppled):
    """The same runs and seed give the same start, bit for bit; another seed another."""
    from tacest.estimation.config import EstimatorConfig
    from tacest.estimation.data import choose_scales
    from tacest.estimation.smc2d import SMCSettings, smc_start

    sc = choose_scales([toppled], EstimatorConfig())
    a = smc_start([toppled], sc.L, sc.m0, SMCSettings(particles=64, seed=5))
    b = smc_start([toppled], sc.L, sc.m0, SMCSettings(particles=64, seed=5))
    c = smc_start([toppled], sc.L, sc.m0, SMCSettings(particles=64, seed=6))
    np.testing.assert_array_equal(a.extents, b.extents)
    np.testing.assert_array_equal(a.poses[0], b.poses[0])
    assert (a.mass, a.mu_ground, a.mu_finger) == (b.mass, b.mu_ground, b.mu_finger)
    assert not np.array_equal(a.poses[0], c.poses[0])


def test_the_sampler_follows_the_topple(toppled):
    """The sampler's best hypothesis turns with the box: its angle at the end is within
    10 degrees of the truth's 90 (a sliding start would stay at 0), and its extents are
    within 25 % (a start, not the estimate: the NLP refines it; measured 9 % and 20 %:
    a hypothesis somewhat taller topples the same way under the same push)."""
    from tacest.estimation.config import EstimatorConfig
    from tacest.estimation.data import choose_scales
    from tacest.estimation.smc2d import SMCSettings, smc_start

    sc = choose_scales([toppled], EstimatorConfig())
    s = smc_start([toppled], sc.L, sc.m0, SMCSettings(particles=256, seed=0))
    turn = np.degrees(np.unwrap(s.poses[0][:, 2])[-1] - s.poses[0][0, 2])
    truth = np.degrees(np.unwrap(toppled.truth.pose[:, 2])[-1] - toppled.truth.pose[0, 2])
    assert abs(turn - truth) < 10.0, (turn, truth)
    np.testing.assert_allclose(s.extents, np.ptp(toppled.truth.vertices, axis=0), rtol=0.25)


#: a gentle recording, contact and normal only, whose first touch lands on the top face
#: 31 mm from the box's centre, near its corner (seed 6: found by scanning seeds 0-9,
#: of which 2, 4, 6 and 9 start so)
TOP_FIRST = dict(object_spec="box", pokes=6, seed=6, poke_style="gentle", force_stream=False)


def test_a_first_touch_on_the_top_face_leaves_the_start_anywhere_under_it():
    """Before its first touch the object rests where the touch puts it: on a side face a
    point, on the top face anywhere under the fingertip (initial_pose_range: half range
    w / 2).  The sampler spreads its hypotheses over that range, so that its best one
    starts where the truth did (within 10 mm; a start centred under the touch was 31 mm
    off, and every hypothesis then failed to follow: log likelihood -2554, now above
    -100), in every run of several."""
    from tacest.estimation.config import EstimatorConfig
    from tacest.estimation.data import choose_scales
    from tacest.estimation.initial import TOP_TOUCH_COS, contact_points, initial_pose_range
    from tacest.estimation.smc2d import SMCSettings, smc_start

    run = record_sim(SimOptions(**TOP_FIRST))
    _, _, points, normals = contact_points(run)
    assert normals[0] @ run.up > TOP_TOUCH_COS  # the recording does what the test is about
    pose, half_range = initial_pose_range(run, 0.1, 0.08)
    assert half_range == 0.05 and abs(pose[0] - points[0][0]) < 1e-12
    sc = choose_scales([run], EstimatorConfig())
    s = smc_start([run], sc.L, sc.m0, SMCSettings(particles=256, seed=0))
    assert abs(s.poses[0][0, 0] - run.truth.pose[0, 0]) < 0.010
    assert s.log_likelihood > -100.0
    # an earlier run of several is re-filtered with the best hypothesis alone: its copies
    # spread over the range find where that run started too (the recording twice)
    s2 = smc_start([run, run], sc.L, sc.m0, SMCSettings(particles=256, seed=0))
    for poses in s2.poses:
        assert abs(poses[0, 0] - run.truth.pose[0, 0]) < 0.010


@pytest.mark.slow
def test_noiseless_known_answer_toppling_box():
    """Six dynamic pokes (seed 0 of the dynamic mix: fast, high and flicking pokes; the
    box topples over one edge, 98 degrees, and slides and spins between touches),
    recorded without sensor noise: the estimate follows the topple and gives back the
    box.  Tolerances: the simulator (pymunk, 20 substeps, its own contact slop) and the
    estimator's model differ by their contact handling (penalties with sigma_gap 0.5 mm),
    so the shape is good to about a millimetre, not to rounding (0.66 mm measured); mass
    and ground friction are seen through the measured force in the topple and the
    slides (1.6 % each measured): 5 %."""
    from tacest.dims import estimate_runs
    from tacest.evaluation.metrics import evaluate

    run = record_sim(SimOptions(object_spec="box", pokes=6, seed=0, poke_style="dynamic", noise_force=0.0,
                                noise_position=0.0, noise_normal=0.0))
    assert _max_tilt_deg(run) > 90.0  # it topples
    est = estimate_runs([run], "box")
    rep = evaluate(est, run, 0)
    assert est.success
    assert rep["chamfer_body"] < 1.5e-3, rep["chamfer_body"]
    assert rep["pose_angle_rmse"] < np.radians(3.0), rep["pose_angle_rmse"]
    assert rep["mass_rel"] < 0.05 and rep["friction_ground_rel"] < 0.05, (rep["mass_rel"], rep["friction_ground_rel"])
    assert est.consistent is True, est.fit_quality
    # calibrated: the shape error within 3 of its reported std
    assert rep["chamfer_body"] <= 3.0 * est.std["shape"], (rep["chamfer_body"], est.std["shape"])


@pytest.mark.xfail(strict=True, reason="known limitation (docs/estimation.md, 'Dynamic pokes'): a single high poke "
                   "that topples the box leaves the NLP in a light, grippy basin 6-9 mm off (mass 45-70 % low) on "
                   "seeds 8, 10 and 11, whose objective is above the truth's (7.2 against 2.8 on seed 8) but whose "
                   "residuals are within the noise: neither sampler start leads to the truth's basin")
def test_a_single_toppling_poke_gives_back_the_box(toppled):
    from tacest.dims import estimate_runs
    from tacest.evaluation.metrics import evaluate

    est = estimate_runs([toppled], "box")
    assert evaluate(est, toppled, 0)["chamfer_body"] < 3e-3


#: a high poke (MuJoCo, 3 fingers) that topples the box over one edge, 96 degrees, in
#: 0.3 s with the fingertip pressing on the top edge (up to 17 N): seed 1 of
#: SimOptions(dim=3, poke_style="high", pokes=2, fingers=3), found by scanning seeds
#: 0-5 (seed 1 topples; the others tip it 24-37 degrees)
TOPPLE_3D = dict(dim=3, object_spec="box", pokes=2, seed=1, fingers=3, poke_style="high")


def _max_rotation_deg(run) -> float:
    q = run.truth.pose[:, 3:7] / np.linalg.norm(run.truth.pose[:, 3:7], axis=1, keepdims=True)
    return float(np.degrees(np.max(2.0 * np.arccos(np.clip(np.abs(q @ q[0]), 0.0, 1.0)))))


def test_noiseless_known_answer_toppling_box_3d():
    """3-D known answer: a box toppled by a fingertip (96 degrees), the finger sensors
    noiseless (force, contact, normal), the pose seen by motion capture at the
    simulator's 0.5 mm / 10 mrad.  The estimate follows the topple and gives back the
    box, its mass and its ground friction, and says the fit is consistent.

    Tolerances: extents 1.5 % (the noiseless tosses' tolerance, tests/test_estimator3d.py:
    MuJoCo's soft contacts against the estimator's penalties; 0.5 mm = 0.5 % seen); mass
    and ground friction 10 % (they are seen through the measured force during the slow
    tip and the slide, 2.8 % and 1.4 % seen); the finger friction and the inertia are not
    asserted (one edge contact carries the topple: finger mu 17 % off, I/m 0.7-2.4x).
    Before the smoothed start (estimator3d.smoothed_start_track) this fit ended in a
    basin with 64 % too much mass and 70x the inertia, marked inconsistent."""
    from tacest.dims import estimate_runs, record_sim
    from tacest.evaluation.metrics import evaluate
    from tacest.sim.record import SimOptions

    run = record_sim(SimOptions(noise_force=0.0, noise_position=0.0, noise_normal=0.0, observe_pose=5e-4,
                                **TOPPLE_3D))
    assert _max_rotation_deg(run) > 90.0  # it topples
    est = estimate_runs([run], "box")
    assert est.success, est.solver_status
    np.testing.assert_allclose(np.ptp(est.vertices, axis=0), np.ptp(run.truth.vertices, axis=0), rtol=0.015)
    rep = evaluate(est, run, 0)
    assert rep["mass_rel"] < 0.10 and rep["friction_ground_rel"] < 0.10, (rep["mass_rel"], rep["friction_ground_rel"])
    assert rep["pose_position_rmse"] < 1e-3 and rep["pose_angle_rmse"] < np.radians(1.0)
    assert est.consistent is True, est.fit_quality
    assert rep["chamfer_body"] <= 3.0 * est.std["shape"], (rep["chamfer_body"], est.std["shape"])

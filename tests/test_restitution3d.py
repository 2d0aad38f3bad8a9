"""restitution in 3-D: the impact law on a stage window of five poses (tacest.model.
effects_contact.Restitution.impacts_3d), the windows and the summed Jacobian scatter it
needs, the time stepper that simulates it, and the estimator recovering e."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.geometry.polytope import box_vertices_3d, polytope_inertia
from tests.test_estimator3d import EXTENTS, FRICTION, MASS, _assert_derivatives_match_finite_differences

INERTIA = polytope_inertia(box_vertices_3d(EXTENTS), MASS)


def test_windows_repeat_a_runs_first_sample():
    """Layout3D.windows: the poses before a run's first sample are that first sample (a
    velocity of 0 there: no approach, no impact memory), never a sample of the run
    before it; three-pose windows are the stage's triples."""
    from tacest.model.stage3d import Layout3D

    lay = Layout3D(lengths=(4, 5), F=0)
    w = lay.windows(5)
    assert w.shape == (lay.M, 5)
    np.testing.assert_array_equal(w[:2], [[0, 0, 0, 1, 2], [0, 0, 1, 2, 3]])
    np.testing.assert_array_equal(w[2:], [[4, 4, 4, 5, 6], [4, 4, 5, 6, 7], [4, 5, 6, 7, 8]])
    np.testing.assert_array_equal(lay.triples, w[:, 2:])


def test_the_jacobian_scatter_sums_blocks_that_share_a_place():
    """assembly.scatter_matrix: local blocks whose inputs repeat one variable (a window
    at a run's start) add up on its column (the chain rule); without repeats the map is
    the permutation it was."""
    from tacest.estimation.assembly import scatter_matrix

    rng = np.random.default_rng(0)
    B, m, n_y = 3, 2, 4
    local = rng.normal(size=(m, n_y * B))
    rows = np.arange(B)[:, None] * m + np.arange(m)
    for cols in (np.array([[0, 0, 1, 2], [0, 1, 2, 3], [1, 2, 3, 4]]),  # repeats in block 0
                 np.array([[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]])):  # none
        n_cols = int(cols.max()) + 1
        J = scatter_matrix([(ca.MX(ca.DM(local)), ca.Sparsity.dense(m, n_y), rows, cols)], B * m, n_cols)
        got = np.asarray(ca.Function("J", [], [ca.densify(J)])()["o0"])
        want = np.zeros((B * m, n_cols))
        for b in range(B):
            for j in range(n_y):
                want[rows[b], cols[b, j]] += local[:, n_y * b + j]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)


def _drop(e, T=80, dt=0.005, drop=0.06, tilt=0.0, noise_seed=None, sigma=5e-4, law=False):
    """A box released at rest ``drop`` m above the ground (rotated by ``tilt`` rad about
    x), simulated by the project's 3-D model with restitution e (pose-only run); e = 0
    is the plain model unless ``law`` (the restitution law at e = 0)."""
    from tacest.estimation.rollout3d import simulate_toss
    from tacest.geometry.transforms import quat_from_axis_angle

    q0 = quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), tilt)
    return simulate_toss("box", EXTENTS, MASS, INERTIA, FRICTION, np.r_[0.0, 0.0, drop + EXTENTS[2] / 2, q0],
                         np.zeros(6), T, dt=dt, effect_params={"restitution.e": e} if (e or law) else None,
                         noise_seed=noise_seed, sigma_position=sigma, sigma_angle=10 * sigma)


@pytest.mark.parametrize("e", [0.0, 0.6])
def test_the_time_stepper_bounces_a_dropped_box_by_its_restitution(e):
    """A flat box dropped 6 cm (1.08 m/s at impact) rises after landing to the height of
    a rebound at e × the approach speed: e_eff = sqrt(2 g apex) / a within 10 % of e
    (measured 0.571 for 0.6: the law's rebound is e·a less what gravity takes in the
    interval after the impact, 1 % of g dt at 5 ms); with the law at e = 0 (its impact
    relief alone, the diagnosis' ablation) it does not rise, and settles within 0.1 s
    (within 0.5 mm of the ground: the contact's penetration tolerance)."""
    run = _drop(e, law=True)  # at e = 0 the law's impact relief alone: it must not bounce
    assert run.extra_attrs["simulation_unconverged_steps"] == 0
    z = run.truth.pose[:, 2] - EXTENTS[2] / 2  # the bottom face's height, m
    landed = int(np.argmax(z < 0.005))  # the last sample before the impact
    apex = float(z[landed + 1:].max())
    a = np.sqrt(2 * 9.81 * 0.06)
    if e == 0:
        # no rebound: never above the height of the last sample before the impact (+0.5 mm,
        # the penetration tolerance); the relief lets it settle over some samples
        # (3.4 mm at the impact, 0.7 mm 35 ms later, on the ground by 0.1 s)
        assert apex < z[landed] + 5e-4, (apex, z[landed])
        assert abs(z[landed + 20]) < 5e-4, z[landed + 20]
    else:
        assert np.sqrt(2 * 9.81 * apex) / a == pytest.approx(e, rel=0.1)


def test_3d_restitution_derivatives_match_finite_differences(monkeypatch):
    """Residual Jacobian, gradient and exact Hessian of the 3-D NLP with restitution
    against central differences, on 12 samples of a bouncing landing that start at the
    run's start (so that the windows repeat its first sample and the summed scatter is
    checked too); the coefficient's column is live at the bounce."""
    monkeypatch.setenv("TACEST_NO_COMPILE", "1")
    from tacest.estimation.estimator3d import Estimator3D

    run = _drop(0.6, T=40)
    a, b = 18, 30  # the impact is at sample 21
    short = run.replace(time=run.time[a:b] - run.time[a], pose_obs=run.pose_obs[a:b], truth=None)
    est = Estimator3D([short], "box", effects=("restitution",))
    # the bounce itself (the smoothed start rounds it off), the box's own size (a start
    # shape 1 cm short puts the bottom 1 cm above the ground: no impact anywhere)
    est.start_tracks = [short.pose_obs]
    est.s0 = est.shape.initial(EXTENTS / est.scales.L)
    pr = est.problem
    assert pr.n_poses == 5 and pr.effects[0] == "restitution"
    _assert_derivatives_match_finite_differences(est)
    # live at the bounce itself (the check's random 1 mm moves at 5 ms spread the
    # approach speeds by ~0.3 m/s, where the law's gates are near 0)
    p = est.params(0.5, 1.0, 1.0, ridge=0.0)
    J = pr.residual_jacobian(est.ground_impulses_nnls(est.initial_guess(), p), p)[1]
    assert np.abs(np.asarray(ca.densify(J[: pr.n_res_data, pr.theta_index("restitution.e")]))).max() > 1.0


@pytest.mark.parametrize("e", [0.3, 0.6])
def test_3d_restitution_is_recovered_from_seen_bounces(e):
    """Known answer: two flat drops of the box seen at 0.5 mm / 5 mrad (the bounces 5 and
    20 mm high), fitted with restitution.  e comes back within 30 % (measured 0.262 ±
    0.041 and 0.496 ± 0.035: the first-order law's rebound is what the stepper's is,
    about 5 % low, and the noise on the approach adds the rest), its std is finite, and
    the fit explains the bounces the plastic model cannot (objective 387 and 495 against
    2590 and 3913).  Both starts of estimator3d.solve_observed_tracks are recorded."""
    from tacest.estimation.estimator3d import estimate_3d

    runs = [_drop(e, T=60, dt=0.0068, noise_seed=s) for s in (0, 1)]
    plain = estimate_3d(runs, "box")
    est = estimate_3d(runs, "box", effects=["restitution"])
    assert est.success, est.solver_status
    assert est.params["restitution.e"] == pytest.approx(e, rel=0.3)
    assert 0 < est.std["restitution.e"] < e
    assert est.objective < 0.5 * plain.objective
    import json

    starts = json.loads(est.extra_attrs["starts"])
    assert [a["start"] for a in starts] == ["smoothed observations", "observations"]
    # the height is told by the resting pose: within 2 mm
    assert np.ptp(est.vertices[:, 2]) == pytest.approx(EXTENTS[2], abs=0.002)


def test_the_planning_model_leaves_restitution_out():
    """The 3-D expected information linearizes stages of three poses: it refuses a model
    whose stage looks further back, and ModelState3 leaves such an effect out of the
    planning model."""
    from tacest.estimation.config import EstimatorConfig
    from tacest.estimation.data import Scales
    from tacest.information.expected3d import ExpectedInformation3D

    with pytest.raises(TacestError, match="restitution"):
        ExpectedInformation3D("box", 1, EstimatorConfig(), ("restitution",), Scales(L=0.1, m0=0.4, g=9.81))


@pytest.mark.parametrize("plain,ablated,blamed", [(3.0, 2.0, False), (3.0, 2.9, True), (30.0, 2.5, True),
                                                    (3.0, 2.2, False)])
def test_restitution_is_blamed_only_if_e_itself_closes_the_gap(plain, ablated, blamed):
    """The 3-D verdict rule's ablation (diagnose3d.ABLATED): restitution relieves the
    contact laws at impacts whatever e is, so its held-out gain is checked again against
    the same fit with e = 0, whose own gap e must close a fifth of (the nested
    comparison).  Restitution 2.0 per sample over 400 held-out samples, floor 1.0: not
    blamed when e = 0 does as well (2.0) or e closes less than a fifth of the ablation's
    gap (2.2: 80 of 480 + 2 floor sigmas 40); blamed when e = 0 loses what e gained
    (2.9), and when the plain model is far off (30) but e = 0 still leaves a gap that e
    closes (2.5: 200 of 640; against the plain model's gap, 11600, it would not count)."""
    from tacest.diagnosis.diagnose3d import NONE, Fit3D, _guards, _rule_terms

    fits = {NONE: Fit3D(name=NONE, params={}, status="ok", seconds=0.0, heldout_loss_per_sample=plain),
            "restitution": Fit3D(name="restitution", params={"restitution.e": 0.5}, status="ok", seconds=0.0,
                                 heldout_loss_per_sample=2.0, ablated_loss_per_sample=ablated)}
    e = {"name": "restitution"}
    e.update(_rule_terms(e, fits, 400, 1.0, plain - 1.0, mass_known=True))
    assert e["improvement"] == pytest.approx(400 * (plain - 2.0))
    assert e["effect_improvement"] == pytest.approx(400 * (ablated - 2.0))
    assert e["counts"] is blamed
    assert e["ablation_guard"] is (not blamed)
    assert any("restitution.e = 0" in g for g in _guards(e)) is (not blamed)


def test_a_failed_ablation_withholds_the_blame_and_says_so():
    """Without the held-out fit at e = 0 (nan: it failed) restitution is not blamed, and
    the reason says the ablation is missing, not that e = 0 does as well."""
    from tacest.diagnosis.diagnose3d import NONE, Fit3D, _guards, _rule_terms

    fits = {NONE: Fit3D(name=NONE, params={}, status="ok", seconds=0.0, heldout_loss_per_sample=3.0),
            "restitution": Fit3D(name="restitution", params={"restitution.e": 0.5}, status="ok", seconds=0.0,
                                 heldout_loss_per_sample=2.0)}
    e = {"name": "restitution"}
    e.update(_rule_terms(e, fits, 400, 1.0, 2.0, mass_known=True))
    assert not e["counts"] and e["ablation_guard"]
    assert any("failed" in g for g in _guards(e))

"""The implicit estimator: exact derivatives, known answers, invariance, failure paths."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import casadi as ca
import numpy as np
import pytest

from tacest.errors import SolveFailedError, TacestError
from tacest.estimation.config import load_config
from tacest.estimation.data import parameter_vector, starts_at_rest
from tacest.dims import estimate_runs
from tacest.estimation.estimator import ImplicitEstimator
from tacest.estimation.initial import initial_guess
from tacest.model.stage2d import SQUARED_TERMS, TERMS
from tacest.geometry.shapes import polygon_sd_and_normal_function
from tacest.io.run import Run
from tests.nlp_checks import assert_derivatives_match_finite_differences

TACEST = str(Path(sys.executable).parent / "tacest")


def pushed_box_run(T=24, k0=8, w=0.1, rad=0.01, speed=0.05, m=0.3, mu=0.4, dt=0.01) -> Run:
    """A box pushed sideways at constant speed after sample k0 (quasi-static sliding):
    finger touching the left face at mid height, normal -x, force mu·m·g along +x."""
    t = np.arange(T) * dt
    x = np.where(np.arange(T) >= k0, speed * (t - t[k0]), 0.0)
    fp = np.zeros((T, 1, 2))
    fp[:, 0, 1] = 0.03
    fp[:, 0, 0] = x - w / 2 - rad
    fp[:k0, 0, 0] -= 0.02 * (1 - np.arange(k0) / k0)
    contact = np.zeros((T, 1), np.uint8)
    contact[k0:] = 1
    normal = np.full((T, 1, 2), np.nan)
    normal[k0:, 0] = [-1.0, 0.0]
    force = np.zeros((T, 1, 2))
    force[k0:, 0] = [mu * m * 9.81, 0.0]
    return Run(dim=2, dt=dt, time=t, gravity=np.array([0.0, -9.81]), finger_position=fp,
               finger_radius=np.array([rad]), contact=contact, normal=normal, force=force,
               prior={"size_bound": 0.3})


def _pose_observed(run: Run, seed=5) -> Run:
    """The run with pose observations (its pushed path, noisy, one row missing), so that
    the pose and Occam terms enter the derivative checks."""
    rng = np.random.default_rng(seed)
    x = run.finger_position[:, 0, 0] + 0.06
    obs = np.column_stack([x, np.full(run.n_samples, 0.03), np.zeros(run.n_samples)])
    obs = obs + rng.normal(size=obs.shape) * [5e-4, 5e-4, 0.01]
    obs[3] = np.nan
    return run.replace(pose_obs=obs, sigma_position=5e-4, sigma_angle=0.01)


def _problem_point(shape, seed=0, observed=False, reach=None):
    """An estimator and a generic point of its NLP; ``observed``: with pose observations
    and the Occam term weighted 1 (its default is 0), so that its derivatives are checked;
    ``reach`` (m): noise.complementarity_reach, 0 off, None the default (the box's upper
    vertices, 6 cm up, are beyond 1 cm, so a reach of 1 cm is active there)."""
    import dataclasses

    from tacest.estimation.config import EstimatorConfig

    run = pushed_box_run()
    config = None
    base = EstimatorConfig()
    if observed:
        run = _pose_observed(run)
        config = dataclasses.replace(base, weights=dataclasses.replace(base.weights, occam=1.0))
    if reach is not None:
        config = (config or base).with_reach(reach)
    est = ImplicitEstimator([run], shape, config)
    pr = est.problem
    rng = np.random.default_rng(seed)
    # a generic point near the start (perturbation 0.02 in scaled units: well inside
    # every smooth region, away from the start's special symmetric values)
    z = initial_guess(pr, [run], est.scales, est.s0) + rng.normal(size=pr.n_z) * 0.02
    p = parameter_vector(pr, [run], est.scales, est.config, 0.5, 2.0, est.s0, ridge=0.0)
    return est, pr, z, p


POINTS = [("box", False, 0.0), ("polygon:5", False, 0.0), ("box", True, 0.0), ("box", False, 0.01)]


@pytest.mark.parametrize("shape,observed,reach", POINTS)
def test_gradient_and_constraint_jacobian_match_finite_differences(shape, observed, reach):
    est, pr, z, p = _problem_point(shape, observed=observed, reach=reach)
    assert_derivatives_match_finite_differences(pr, z, p)


@pytest.mark.parametrize("shape,observed,reach", POINTS)
def test_exact_hessian_blocks_match_casadi(shape, observed, reach):
    """The O(T) block-assembled Hessian equals CasADi's Hessian of the whole Lagrangian."""
    est, pr, z, p = _problem_point(shape, observed=observed, reach=reach)
    lam_g = np.random.default_rng(2).normal(size=pr.g.shape[0])
    mine = np.asarray(ca.DM(pr.hess_lag["exact"](z, p, 0.7, lam_g)))
    # the objective through the compiled per-sample kernels (pr.f) and through the SX
    # functions (pr.f_reference, differentiable to second order) are the same function
    fs = ca.Function("fs", [pr.z_sym, pr.p_sym], [pr.f, pr.f_reference])(z, p)
    assert float(fs[0]) == pytest.approx(float(fs[1]), rel=1e-12)
    lag = 0.7 * pr.f_reference + ca.dot(ca.DM(lam_g), pr.g)
    ref = np.asarray(ca.DM(ca.Function("h", [pr.z_sym, pr.p_sym],
                                       [ca.triu(ca.hessian(lag, pr.z_sym)[0])])(z, p)))
    # both are exact symbolic derivatives: they differ by rounding only (entries ~1e6)
    np.testing.assert_allclose(mine, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize("observed", [False, True])
def test_gauss_newton_hessian_is_jtj(observed):
    """Gauss–Newton model: J_rᵀJ_r of the squared terms and of the priors' residuals, plus
    the exact Hessian of the penalty (Occam) term."""
    est, pr, z, p = _problem_point("box", observed=observed)
    gn = np.asarray(ca.DM(pr.hess_lag["gauss-newton"](z, p, 1.0, np.zeros(pr.g.shape[0]))))
    w = pr.weight_sym
    r = ca.vertcat(*[ca.sqrt(w[TERMS.index(t)]) * pr.residual_stack[t] for t in SQUARED_TERMS])
    J = np.asarray(ca.DM(ca.Function("J", [pr.z_sym, pr.p_sym], [ca.jacobian(r, pr.z_sym)])(z, p)))
    prior = pr.p_sym[pr.n_p + len(TERMS): pr.n_p + len(TERMS) + pr.n_prior()]
    Jp = ca.jacobian(pr.prior_residual(pr.z_sym[: pr.n_theta], prior), pr.z_sym)
    hp = ca.Function("hp", [pr.z_sym, pr.p_sym], [ca.triu(ca.mtimes(Jp.T, Jp))])
    hpen = ca.Function("hpen", [pr.z_sym, pr.p_sym], [ca.triu(ca.hessian(pr.f_penalty_reference, pr.z_sym)[0])])
    pen = np.asarray(ca.DM(hpen(z, p)))
    assert (np.abs(pen).max() > 0) == observed  # the Occam term acts on pose-observed runs only
    ref = np.triu(J.T @ J) + np.asarray(ca.DM(hp(z, p))) + pen
    np.testing.assert_allclose(gn, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def test_a_run_observed_at_its_first_sample_starts_free():
    """The rest prior holds v[0] only where nothing measures it: a run whose sample 0 is
    pose-observed (a toss seen by motion capture) starts free, whatever its velocity;
    the same run with row 0 missing, and a run without observations, start at rest
    (their sample-0 dynamics term is 0.5·|v0 / σ_rest|², hand-computed below)."""
    run = pushed_box_run()
    free = _pose_observed(run)
    obs = free.pose_obs.copy()
    obs[0] = np.nan
    held = free.replace(pose_obs=obs)
    assert not starts_at_rest(free) and starts_at_rest(held) and starts_at_rest(run)
    est = ImplicitEstimator([free, held, run], "box")
    z = initial_guess(est.problem, est.runs, est.scales, est.s0)
    est.p_final = est.params(0.5, 2.0)
    v0__world = np.array([0.3, -0.2, 1.5])  # m/s, m/s, rad/s
    sig = est.config.noise.rest
    L = est.scales.L
    for i in range(3):
        Q, V, _, _ = est.problem.run_blocks(z, i)
        V = V.copy()
        V[:, 0] = v0__world / np.array([L, L, 1.0])
        est.problem.set_run_blocks(z, i, V=V)
    expected = 0.5 * np.sum((v0__world / np.array([sig, sig, 2 * sig / L])) ** 2)
    first = [est.per_sample_residuals(z, i)["dynamics"][0] for i in range(3)]
    assert first[0] == 0.0
    # rtol 1e-12: the same arithmetic in CasADi and NumPy, rounding only
    assert first[1] == pytest.approx(expected, rel=1e-12) and first[2] == pytest.approx(expected, rel=1e-12)


def test_signed_distance_hand_table_and_normal():
    """Unit square [-0.5, 0.5]²: outside a face, outside a corner, inside; the normal is the
    gradient of the signed distance (checked against central differences)."""
    fun = polygon_sd_and_normal_function(4)
    V = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    table = [((0.8, 0.1), 0.3, (1, 0)), ((1.5, 1.5), np.sqrt(2), (np.sqrt(0.5), np.sqrt(0.5))),
             ((0.1, -0.3), -0.2, (0, -1)), ((-0.5, 0.0), 0.0, (-1, 0))]
    for p, sd_true, n_true in table:
        sd, n = fun(p, V)
        assert float(sd) == pytest.approx(sd_true, abs=1e-9)
        np.testing.assert_allclose(np.asarray(n).ravel(), n_true, atol=1e-9)
    # gradient vs finite differences at generic points (h = 1e-7: smooth there)
    for p in [(0.9, 0.2), (-0.7, 0.9), (0.2, 0.1)]:
        _, n = fun(p, V)
        fd = [(float(fun(np.add(p, e), V)[0]) - float(fun(np.subtract(p, e), V)[0])) / 2e-7
              for e in ([1e-7, 0], [0, 1e-7])]
        np.testing.assert_allclose(np.asarray(n).ravel(), fd, atol=1e-6)


def test_bad_runs_are_refused():
    run = pushed_box_run()
    with pytest.raises(TacestError, match="3-D"):
        estimate_runs([run.replace(dim=3)], "box")
    with pytest.raises(TacestError, match="unknown shape"):
        estimate_runs([run], "blob")
    with pytest.raises(TacestError, match="no run"):
        estimate_runs([], "box")


def test_failed_solve_is_reported_and_exits_2(tmp_path):
    from tacest.io.run import write_run

    run_path = tmp_path / "run.h5"
    write_run(pushed_box_run(T=40, k0=10), run_path)
    cfg = tmp_path / "tight.toml"
    cfg.write_text("[solver]\nmax_iter = 1\nstage_max_iter = 1\n")
    with pytest.raises(SolveFailedError, match="IPOPT failed"):
        estimate_runs([__import__("tacest.io.run", fromlist=["read_run"]).read_run(run_path)], "box",
                      config=load_config(cfg))
    out = tmp_path / "est.h5"
    proc = subprocess.run([TACEST, "estimate", str(run_path), "--config", str(cfg), "-o", str(out), "--quiet"],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "IPOPT failed" in proc.stderr
    assert "Traceback" not in proc.stderr and not out.exists()


@pytest.mark.slow
def test_known_answer_box_from_six_pokes(tmp_path):
    """A simulated 8.7 × 10.9 cm box, six pokes, default sensor noise (seed 1): the
    estimate places the shape within the issue's 3 mm Chamfer target, the file round-trips
    and eval reads it."""
    from tacest.evaluation.metrics import evaluate
    from tacest.io.estimate import read_estimate, write_estimate
    from tacest.io.run import read_run, write_run
    from tacest.sim.record import SimOptions, record_sim

    run_path = tmp_path / "run.h5"
    write_run(record_sim(SimOptions(object_spec="box", seed=1, pokes=6)), run_path)
    run = read_run(run_path)
    est = estimate_runs([run], "box")
    assert est.success and est.solver_status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
    write_estimate(est, tmp_path / "est.h5")
    back = read_estimate(tmp_path / "est.h5")
    metrics = evaluate(back, run)
    assert metrics["chamfer"] <= 3e-3, metrics
    assert back.information is not None and back.information.shape[0] == len(back.info_names)
    for term in ("force", "normal", "contact", "dynamics", "complementarity"):
        assert back.runs[0].residuals[term].shape == (run.n_samples,)


@pytest.mark.slow
def test_noiseless_known_answer_box():
    """Noiseless recording (no force, position or normal noise; seed 7, a 12.2 × 6.9 cm
    box pushed from the side and pressed from above): shape, mass and both frictions
    come back close to the truth.  Tolerances: the model is not the simulator's (pymunk's
    contact solver, finite substeps, the model's smoothing: complementarity tolerance of
    0.5 mm, |slip| smoothed below 3 mm/s), so even without noise the answer is not exact.
    1 mm of Chamfer is a third of the issue's target for noisy data; frictions within
    10 %, two thirds of its 15 %; the mass within the issue's 15 %: it is seen mostly in
    the force transients at contact onset, which a time-stepping model resolves to one
    sample.  Measured: 0.3 mm, mass 8.8 %, ground friction 2.7 %, finger friction 0.7 %."""
    from tacest.evaluation.metrics import evaluate
    from tacest.sim.record import SimOptions, record_sim

    run = record_sim(SimOptions(object_spec="box", seed=7, pokes=6, noise_force=0.0, noise_position=0.0,
                                noise_normal=0.0))
    est = estimate_runs([run], "box")
    assert est.success
    m = evaluate(est, run)
    assert m["chamfer"] <= 1e-3, m
    for key, tol in (("mass_rel", 0.15), ("friction_ground_rel", 0.10), ("friction_finger_rel", 0.10)):
        assert m[key] <= tol, (key, m)


@pytest.mark.slow
def test_horizontal_shift_of_the_scene_shifts_the_estimate(tmp_path):
    """Invariance: the same recording moved 0.25 m along the ground gives the same shape
    and the trajectory moved by 0.25 m."""
    from tacest.sim.record import SimOptions, record_sim

    run = record_sim(SimOptions(object_spec="box", seed=1, pokes=3))
    shift = np.array([0.25, 0.0])
    moved = run.replace(finger_position=run.finger_position + shift)
    a = estimate_runs([run], "box")
    b = estimate_runs([moved], "box")
    # identical problems up to floating-point rounding of the shifted coordinates; the
    # nonconvex solve may take slightly different paths: 0.5 mm (a twentieth of the
    # Chamfer target) bounds what such rounding-level differences can move
    np.testing.assert_allclose(np.sort(np.abs(a.vertices.ravel())), np.sort(np.abs(b.vertices.ravel())), atol=5e-4)
    np.testing.assert_allclose(b.runs[0].pose[:, :2] - a.runs[0].pose[:, :2], np.tile(shift, (run.n_samples, 1)),
                               atol=5e-4)


def test_start_shape_candidates_are_distinct_and_best_first():
    from tacest.estimation.initial import DISTINCT_EXTENT_RATIO, choose_start_shape, start_shape_candidates
    from tacest.geometry.shapes import numeric_vertices

    run = pushed_box_run()
    est = ImplicitEstimator([run], "box")
    cands = start_shape_candidates(est.problem, [run], est.scales, est.s0, 4)
    assert len(cands) == 4
    np.testing.assert_array_equal(cands[0], choose_start_shape(est.problem, [run], est.scales, est.s0))
    ext = [np.ptp(numeric_vertices(est.shape, c, est.scales.L), axis=0) for c in cands]
    for i in range(len(ext)):
        for j in range(i):
            # distinct: some extent differs by more than the ratio (exact arithmetic on the grid)
            assert np.max(np.abs(np.log(ext[i] / ext[j]))) > np.log(DISTINCT_EXTENT_RATIO)


def test_restarts_keep_the_lowest_objective_and_skip_consistent_fits(monkeypatch):
    run = pushed_box_run()
    # defaults: the sampler's starts are all solved (solver.sampler_starts, fewer when
    # two find the same box); a clean pushed box is consistent, so no restart follows
    est = ImplicitEstimator([run], "box")
    out = est.solve()
    assert 1 <= len(est.attempts) <= est.config.solver.sampler_starts
    assert all(a["start"] == "sampler" for a in est.attempts)
    assert all(a["misfit_local"] for a in est.attempts)
    assert out.objective == min(a["objective"] for a in est.attempts)
    # push-tracked starts only, a physics threshold no fit meets and fits whose data say
    # they are wrong (beyond a local misfit): every start is tried, the best is kept
    cfg = load_config(None, overrides={"solver": {"restarts": 2, "restart_physics": 1e-12, "sampler_particles": 0}})
    est = ImplicitEstimator([run], "box", cfg)
    monkeypatch.setattr(est, "fit_quality", lambda z: SimpleNamespace(local=False))
    out = est.solve()
    assert len(est.attempts) == 3
    ok = [a["objective"] for a in est.attempts if a["status"] not in ("failed", "abandoned")]
    assert ok and out.objective == min(ok)
    # the returned z is that fit's: its physics measure is the one recorded for it
    kept = next(a for a in est.attempts if a.get("objective") == out.objective)
    assert est.physics_per_sample(out.z) == pytest.approx(kept["physics_per_sample"], rel=1e-9)
    with pytest.raises(TacestError, match="restart"):
        load_config(None, overrides={"solver": {"restarts": -1}})


@pytest.mark.parametrize("T", [1, 2, 5, 7, 8, 57])
def test_fingertip_velocity_is_the_least_squares_slope_of_its_window(T):
    """data.finger_velocity (full windows at once, shorter ones at the ends) equals
    np.polyfit's slope of degree 1 over each sample's window of 2·h+1 samples (fewer at
    the ends, 0 for a single sample) to 1e-9 of the values' scale (polyfit's own
    rounding); a NaN position spoils only the windows that hold it."""
    from types import SimpleNamespace

    from tacest.estimation.data import FINGER_VELOCITY_HALF_WIDTH as h, finger_velocity

    rng = np.random.default_rng(T)
    fp = rng.normal(size=(T, 2, 3)).cumsum(axis=0)
    if T > 5:
        fp[5, 1, 0] = np.nan
    dt = 0.01
    got = finger_velocity(SimpleNamespace(finger_position=fp, dt=dt))
    for t in range(T):
        a, b = max(0, t - h), min(T, t + h + 1)
        for f in range(2):
            for d in range(3):
                y = fp[a:b, f, d]
                want = 0.0 if b - a < 2 else (np.nan if np.isnan(y).any() else
                                              np.polyfit(np.arange(a, b) * dt, y, 1)[0])
                np.testing.assert_allclose(got[t, f, d], want, atol=1e-9 * np.nanmax(np.abs(fp)) / dt)


@pytest.mark.parametrize("T", [4, 9, 10, 57])
def test_the_local_quadratic_smoother_is_savitzky_golay(T):
    """initial.smooth_quadratic (numpy) equals SciPy's savgol_filter of order 2 with
    mode "interp" to rounding (1e-12 of the values' scale), also at a window as long as
    the data, and leaves data shorter than its window alone."""
    from scipy.signal import savgol_filter

    from tacest.estimation.initial import smooth_quadratic

    x = np.random.default_rng(T).normal(size=(T, 3)).cumsum(axis=0)
    got = smooth_quadratic(x, 0.01, 0.07)  # a 9-sample window
    want = savgol_filter(x, 9, 2, axis=0, mode="interp") if T >= 9 else x
    np.testing.assert_allclose(got, want, atol=1e-12 * np.abs(x).max())


def test_observed_trajectory_interpolates_unwraps_and_smooths_without_bias():
    from tacest.estimation.initial import OBSERVED_SMOOTHING_S, observed_trajectory

    run = pushed_box_run(T=60)
    t = np.arange(run.n_samples) * run.dt
    # a quadratic in every coordinate, the angle crossing ±pi (wrapped as observed)
    true = np.stack([0.1 + 0.2 * t - 0.3 * t**2, 0.05 + 0.1 * t**2, 3.0 + 2.0 * t + 1.5 * t**2], axis=1)
    obs = true.copy()
    obs[:, 2] = np.angle(np.exp(1j * true[:, 2]))
    assert np.any(np.abs(np.diff(obs[:, 2])) > np.pi)  # the observations do wrap
    run.pose_obs = obs
    assert OBSERVED_SMOOTHING_S / run.dt >= 5  # the smoother is in use at this rate
    # the local quadratic reproduces a quadratic: only rounding (1e-9 of O(1) values)
    np.testing.assert_allclose(observed_trajectory(run), true, atol=1e-9)
    # missing rows are interpolated: a linear motion survives interpolation and smoothing
    lin = np.stack([0.1 + 0.2 * t, 0.05 + 0 * t, 0.5 - 1.0 * t], axis=1)
    run.pose_obs = lin.copy()
    run.pose_obs[10:25] = np.nan
    run.pose_obs[:3] = np.nan  # before the first observed row: held at that row
    got = observed_trajectory(run)
    half = int(round(OBSERVED_SMOOTHING_S / run.dt / 2))  # the smoother's half-window
    # beyond the rows held before the first observation (constant), and a half-window
    # of the smoother from them, the line is reproduced up to rounding
    np.testing.assert_allclose(got[3 + half:], lin[3 + half:], atol=1e-9)
    assert np.all(np.isfinite(got))
    # no usable observations: no observed trajectory
    run.pose_obs = np.full_like(lin, np.nan)
    run.pose_obs[5] = lin[5]
    assert observed_trajectory(run) is None
    run.pose_obs = None
    assert observed_trajectory(run) is None


def _pose_observed_pushes(seed: int, speed: float, height: float):
    """A clean box, pose observed at 0.5 mm, pushed twice (from +x, then from -x) at
    ``speed`` m/s, ``height`` × its height above the centroid, 5 cm past the touch."""
    from tacest.sim.record import SimOptions, initial_state, simulate_aimed_pokes

    def aim(i, st):
        world = st.world()
        c, verts = world.centroid__world(), world.vertices__world()
        target = c + np.array([0.0, height * np.ptp(verts[:, 1])])
        return np.array([0.0, (0.0, np.pi)[i], target[0], target[1], 0.05, speed])

    opts = SimOptions(object_spec="box", seed=seed, pokes=0, observe_pose=5e-4)
    return simulate_aimed_pokes(aim, 2, opts, state=initial_state(opts))


def _max_tilt(run) -> float:
    """Largest rotation (rad) of the true object from its starting angle."""
    return float(np.max(np.abs(np.angle(np.exp(1j * (run.truth.pose[:, 2] - run.truth.pose[0, 2]))))))


@pytest.mark.slow
def test_known_answer_toppled_box_with_observed_poses():
    """Pose-observed toppling (tipping, a fall onto the next face, landing): mass and
    ground friction recovered.  Before the observed start, fits of fast high pushes
    went to mass 0.27-0.37 kg for 0.8 and ground friction 2.0 (its bound)."""
    run = _pose_observed_pushes(seed=3, speed=0.3, height=0.48)
    assert _max_tilt(run) > np.radians(60)  # it topples (else the test shows nothing new)
    est = estimate_runs([run], "box")
    assert est.success
    # 15 %: the accuracy target of the estimator's benchmark for mass and friction
    assert est.params["mass"] == pytest.approx(run.truth.mass, rel=0.15)
    assert est.params["friction_ground"] == pytest.approx(run.truth.friction_ground, rel=0.15)
    # the observed poses fix the extents: 3 mm, the benchmark's Chamfer target
    np.testing.assert_allclose(np.sort(np.ptp(est.vertices, axis=0)),
                               np.sort(np.ptp(np.asarray(run.truth.vertices), axis=0)), atol=3e-3)


@pytest.mark.slow
@pytest.mark.xfail(reason="known limitation (docs/estimation.md, 'Pose observations and light objects'): "
                          "slow sliding pushes do not split the push force into mass and ground friction; "
                          "without the Occam term the fit is a massless object with ground friction 2, "
                          "with it 0.046 kg for 0.231 (reported as not identifiable)")
def test_pose_observed_sliding_box_does_not_collapse_to_a_massless_object():
    run = _pose_observed_pushes(seed=4, speed=0.15, height=0.4)
    est = estimate_runs([run], "box")
    assert est.params["mass"] == pytest.approx(run.truth.mass, rel=0.15)


@pytest.mark.slow
def test_a_fit_at_a_parameter_bound_is_not_presented_as_identified():
    """Whatever the fit of the pushes above gives, a mass or ground friction off by more
    than the benchmark's 15 % is not reported as identifiable (without the Occam term: a
    massless object with ground friction at its bound 2.0; with it, 0.046 kg and 0.88
    for 0.231 and 0.24, which the data alone would move by 10 and 7 std: set by the
    term, estimator.OCCAM_SHIFT_SIGMAS)."""
    run = _pose_observed_pushes(seed=4, speed=0.15, height=0.4)
    est = estimate_runs([run], "box")
    for name, true in (("mass", run.truth.mass), ("friction_ground", run.truth.friction_ground)):
        if abs(est.params[name] / true - 1) > 0.15:
            assert not est.identifiable[name], (name, est.params[name], true)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 6])
def test_the_occam_term_stops_the_light_object_collapse(seed):
    """Pushes high on the box (0.3 m/s, 45 % up), poses observed at 0.5 mm: without the
    Occam term (weights.occam = 0) these fits collapse to a massless object with ground
    friction 2.0 (0.002 kg for 0.285 and 0.373; 4 of seeds 0-7 do), with it (the
    default) they keep the true mass and report it as identified."""
    import dataclasses

    from tacest.estimation.config import EstimatorConfig

    run = _pose_observed_pushes(seed=seed, speed=0.3, height=0.45)
    est = estimate_runs([run], "box")
    assert est.success
    # 15 %: the accuracy target of the estimator's benchmark for mass and friction
    assert est.params["mass"] == pytest.approx(run.truth.mass, rel=0.15)
    assert est.identifiable["mass"]
    if seed == 6:  # the control: the same fit without the term collapses
        base = EstimatorConfig()
        off = estimate_runs([run], "box", dataclasses.replace(base, weights=dataclasses.replace(base.weights,
                                                                                                occam=0.0)))
        assert off.params["mass"] < 0.1 * run.truth.mass


@pytest.mark.slow
def test_known_answer_box_from_tosses_seen_by_motion_capture():
    """Free starts: two tosses of one box (released in the air, seen by motion capture at
    0.5 mm, each followed by one random poke; seed 0, a 13.1 × 10.5 cm box of 0.82 kg).
    The estimate gives back the release velocity that no rest prior holds any more, the
    shape, mass and ground friction.  Tolerances: the release velocity within 5 % of its
    speed (the observations fix it to ~0.5 mm / 10 ms = 0.05 m/s per sample, averaged over
    the flight's ~25 samples by the ballistic dynamics: ~1 % of the 1-2 m/s speeds, and
    the spin to ~0.01 rad / 10 ms / sqrt(25) = 0.2 rad/s of 2-10; measured 0.3-0.6 % and
    0.09-0.22 rad/s); the shape within 1 mm of Chamfer (a third of the issue's 3 mm
    target; measured 0.05 mm); mass and ground friction within 10 % (the issue's 15 %
    with room; measured 4.2 % and 5.7 %: two slow random pokes carry the force data)."""
    from tacest.evaluation.metrics import evaluate
    from tacest.sim.record import SimOptions, record_sim, simulate_pokes, state_from_run, toss_state

    opts = SimOptions(object_spec="box", seed=0, pokes=1, observe_pose=5e-4, toss=True)
    first = record_sim(opts)
    second_release = toss_state(state_from_run(first), np.random.default_rng(11), x=0.0)
    second = simulate_pokes(second_release, np.asarray(first.actions.params), opts, noise_key=7, settle_first=True)
    runs = [first, second]
    est = estimate_runs(runs, "box")
    assert est.success
    for run, er in zip(runs, est.runs):
        v_true = (run.truth.pose[1] - run.truth.pose[0]) / run.dt  # the flight's first interval
        v_est = er.velocity[1]
        assert np.linalg.norm(v_est[:2] - v_true[:2]) <= 0.05 * np.linalg.norm(v_true[:2]), (v_est, v_true)
        assert abs(v_est[2] - v_true[2]) <= 0.05 * abs(v_true[2]) + 0.2, (v_est, v_true)
    m = evaluate(est, first)
    assert m["chamfer_body"] <= 1e-3, m
    assert m["mass_rel"] <= 0.10 and m["friction_ground_rel"] <= 0.10, m

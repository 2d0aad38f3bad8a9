"""Expected information, scores, the planner, `tacest plan` and `tacest explore`.

Every case uses short synthetic predictions or estimates made from a simulated run's
truth (no IPOPT solve), so the file stays quick.
"""

from __future__ import annotations

import logging

import json
import math
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from tacest.errors import SolveFailedError, TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import Scales, parameter_vector, touching
from tacest.estimation.problem2d import Problem2D, RunStructure
from tacest.geometry.polygon import box_vertices, polygon_centroid, polygon_inertia
from tacest.geometry.shapes import make_shape
from tacest.information.expected import (MEASUREMENT_TERMS, ExpectedInformation, ModelState, information_names_for,
                                         past_information, predict_poke, prior_information, schur_information)
from tacest.estimation.uncertainty import fold_lifted_parameters
from tacest.information.scores import score
from tacest.io.estimate import Estimate, RunEstimate, read_estimate, write_estimate
from tacest.io.plan import read_plan
from tacest.io.run import read_run, write_run

TACEST = str(Path(sys.executable).parent / "tacest")
L, M0 = 0.1, 0.5  # the estimator's default scales (config prior size and mass)
CONFIG = EstimatorConfig()


def _box_model(x=0.0):
    V = box_vertices(0.1, 0.06)
    m = 0.4
    return ModelState(shape=make_shape("box"), vertices=V, mass=m, inertia=polygon_inertia(V, m),
                      friction_ground=0.5, friction_finger=0.3, pose=np.array([x, 0.03, 0.0]),
                      p_finger__world=np.array([[x, 0.15]]), finger_radius=np.array([0.01]), dt=0.01)


def _polygon_model():
    from tacest.sim.objects import rest_angle, resting_pose

    ang = np.linspace(0, 2 * np.pi, 6)[:-1] + 0.3
    V = np.stack([0.05 * np.cos(ang), 0.04 * np.sin(ang)], 1)
    V = V - polygon_centroid(V)
    m = 0.4
    pose = resting_pose(V, rest_angle(V, None, preferred=0.0), x=0.01)
    return ModelState(shape=make_shape("polygon:5"), vertices=V, mass=m, inertia=1.1 * polygon_inertia(V, m),
                      friction_ground=0.5, friction_finger=0.3, pose=pose, p_finger__world=np.array([[0.0, 0.15]]),
                      finger_radius=np.array([0.01]), dt=0.01)


def _poke(model, angle_deg, depth=0.02):
    x, y = model.centroid__world
    return np.array([0, math.radians(angle_deg), x, y, depth, (0.02 + depth) / 1.0])


_INFO = {}


def _info(spec):
    if spec not in _INFO:
        _INFO[spec] = ExpectedInformation(spec, 1, CONFIG, L, M0)
    return _INFO[spec]


def _observed_route(model, lin):
    """The prediction as observed.py sees a recording: a Problem2D of its length, the
    decision vector at the linearization point, the residual Jacobian with the lifted
    parameters folded into theta."""
    spec = model.shape.name
    T = lin.Q.shape[1]
    pr = Problem2D(make_shape(spec), [RunStructure(T, 1)], CONFIG)
    z = np.zeros(pr.n_z)
    z[: pr.n_theta] = lin.theta
    z[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(pr.phys_sx(lin.theta, L, M0)).ravel()
    pr.set_run_blocks(z, 0, Q=lin.Q, V=lin.V, LG=lin.LG, LF=lin.LF)
    eps, cm, dm = CONFIG.solver.homotopy[-1]
    p = parameter_vector(pr, [lin.run], Scales(L, M0, 9.81), CONFIG, eps, cm, lin.theta[: pr.n_shape], dyn_mult=dm)
    return pr, z, p


# ---------------------------------------------------------------------------------
# information matrices


@pytest.mark.parametrize("make", [_box_model, _polygon_model], ids=["box", "polygon5"])
def test_information_matches_finite_differences_and_observed_construction(make):
    """The Jacobian of the whitened residuals with respect to theta (through the lifted
    physical parameters) and the start pose matches central differences of the
    residuals; F equals the Schur complement built the way observed.py builds I_obs."""
    model = make()
    info = _info(model.shape.name)
    lin = info.linearize(model, predict_poke(model, _poke(model, 35)))
    pr, z, p = _observed_route(model, lin)
    rj = pr.residual_jacobian
    r, J = rj(z, p)
    # the same residuals, whichever route built them (order differs: compare norms)
    assert np.linalg.norm(np.asarray(r)) == pytest.approx(np.linalg.norm(lin.r), rel=1e-12)
    Jf = fold_lifted_parameters(pr, J.sparse(), z, p)
    qa = pr.offsets[0]["Q"][0]
    keep = list(range(pr.n_theta)) + [qa, qa + 1, qa + 2]

    def r_of(delta):
        zz = z.copy()
        th = lin.theta + delta[: pr.n_theta]
        zz[: pr.n_theta] = th
        zz[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(pr.phys_sx(th, L, M0)).ravel()
        zz[qa: qa + 3] += delta[pr.n_theta:]
        return np.asarray(rj(zz, p)[0]).ravel()

    # central differences, h = 1e-6 in scaled units (O(1) values): truncation ~h²·r''' and
    # rounding ~1e-16·|r|/h are both below 1e-8 of a column's norm at this smooth point;
    # 1e-6 leaves a wide margin
    h = 1e-6
    Jd = Jf[:, keep].toarray()
    for k in range(len(keep)):
        e = np.zeros(len(keep))
        e[k] = h
        fd = (r_of(e) - r_of(-e)) / (2 * h)
        assert np.linalg.norm(fd - Jd[:, k]) <= 1e-6 * max(np.linalg.norm(Jd[:, k]), 1e-9), k
    # F by observed.py's construction (finger impulses fixed where the flag is 0)
    fixed = np.zeros(pr.n_z, bool)
    a, n = pr.offsets[0]["LF"]
    fixed[a: a + n] = ~np.repeat(touching(lin.run)[1:], 2, axis=1).reshape(-1)
    is_keep = np.zeros(pr.n_z, bool)
    is_keep[keep] = True
    is_keep[pr.phys_offset: pr.phys_offset + pr.n_phys] = True
    ref = schur_information(Jd, Jf[:, np.nonzero(~is_keep & ~fixed)[0]])
    mine = schur_information(lin.Ja, lin.Jx)
    # identical sums in a different order: rounding of entries up to ~1e12 (the tight
    # kinematics sigma) through one sparse factorization; 1e-6 relative is far above it
    np.testing.assert_allclose(mine, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    F = info.fisher(model, predict_poke(model, _poke(model, 35)))
    assert F.shape == (len(info.names), len(info.names))
    assert np.allclose(F, F.T) and np.linalg.eigvalsh(F).min() >= -1e-9 * np.abs(F).max()


def test_identity_information_matches_finite_differences():
    """Quasi-static identity-Jacobian F: the measurement residuals differentiated with
    every pose moved rigidly with the start pose (∂q_t/∂s = I) and theta (∂q_t/∂θ = 0)."""
    model = _box_model()
    info = _info("box")
    pred = predict_poke(model, _poke(model, 60))
    lin = info.linearize(model, pred)
    pr, z, p = _observed_route(model, lin)
    w = pr.weight_sym
    from tacest.model.stage2d import TERMS

    r_meas = ca.Function("rm", [pr.z_sym, pr.p_sym],
                         [ca.vertcat(*[ca.sqrt(w[TERMS.index(t)]) * pr.residual_stack[t] for t in MEASUREMENT_TERMS])])
    off = pr.offsets[0]["Q"][0]
    T = lin.Q.shape[1]

    def r_of(delta):
        zz = z.copy()
        th = lin.theta + delta[: pr.n_theta]
        zz[: pr.n_theta] = th
        zz[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(pr.phys_sx(th, L, M0)).ravel()
        zz[off: off + 3 * T] += np.tile(delta[pr.n_theta:], T)
        return np.asarray(r_meas(zz, p)).ravel()

    h = 1e-6  # as in the test above
    n = pr.n_theta + 3
    Jfd = np.stack([(r_of(h * e) - r_of(-h * e)) / (2 * h) for e in np.eye(n)], 1)
    ref = info.to_physical(Jfd.T @ Jfd, model)
    mine = info.identity(model, pred)
    np.testing.assert_allclose(mine, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    names = info.names
    for k in ("mass", "inertia_log_ratio", "friction_ground", "friction_finger"):
        assert mine[names.index(k), names.index(k)] == 0.0  # only dynamics connects these to data


def test_a_sticking_poke_adds_no_ground_friction_information():
    """A finger pressing a resting box from above (it sticks: nothing slides) says nothing
    about the ground friction; a poke that slides the box does.  The ground impulses of
    the prediction are fitted inside the friction cone, not on its edge, where the cone
    penalty's slope would pass for information about mu_ground."""
    model = _box_model()
    info = _info("box")
    k = info.names.index("friction_ground")
    slide = predict_poke(model, _poke(model, 20))
    assert abs(slide.pose[-1, 0] - slide.pose[0, 0]) > 0.005  # it slides (~19 mm)
    F_slide = info.fisher(model, slide)[k, k]
    assert F_slide > 0
    for angle in (60, 90):
        press = predict_poke(model, _poke(model, angle))
        assert np.abs(press.pose[-1, :2] - press.pose[0, :2]).max() < 1e-4  # it sticks
        # 1e-6 of a sliding poke's: the fit on the cone's edge gave ~2e-2 of it (100-200
        # against ~5e3), the fit inside the cone ~1e-11
        assert info.fisher(model, press)[k, k] <= 1e-6 * F_slide, angle


# ---------------------------------------------------------------------------------
# scores and the discount by past information


def test_scores_properties():
    rng = np.random.default_rng(0)
    n = 6
    X = rng.normal(size=(n, n))
    I_past = X @ X.T + n * np.eye(n)
    Y = rng.normal(size=(n, 2))
    F = Y @ Y.T  # rank 2, positive semi-definite
    for kind in ("logdet", "A", "E"):
        assert score(np.zeros((n, n)), I_past, kind) == pytest.approx(0.0, abs=1e-12)
        assert score(F, I_past, kind) > 0
    # logdet = log det(F I⁻¹ + I) (definition) and invariant to the rows' units
    assert score(F, I_past) == pytest.approx(np.linalg.slogdet(F @ np.linalg.inv(I_past) + np.eye(n))[1], rel=1e-10)
    S = np.diag(10.0 ** rng.uniform(-3, 3, n))
    assert score(S @ F @ S, S @ I_past @ S) == pytest.approx(score(F, I_past), rel=1e-8)
    assert score(S @ F @ S, S @ I_past @ S, "A") == pytest.approx(score(F, I_past, "A"), rel=1e-8)
    # D ranks as logdet: the difference does not depend on F
    G = F + np.outer(Y[:, 0], Y[:, 0])
    assert score(F, I_past, "D") - score(F, I_past) == pytest.approx(score(G, I_past, "D") - score(G, I_past),
                                                                       rel=1e-9)
    assert 0 < score(F, I_past, "A") <= n
    with pytest.raises(TacestError, match="unknown score"):
        score(F, I_past, "Z")


def test_a_poke_at_an_already_known_face_scores_lower():
    """A box whose left face has been poked again and again: poking the left face once
    more scores below poking the right face or the top.  With the prior alone, left and
    right pokes (mirror images) score the same: the discount comes from I_past."""
    model = _box_model()
    info = _info("box")
    F = {a: info.fisher(model, predict_poke(model, _poke(model, a))) for a in (20, 90, 160)}  # right, top, left
    prior = prior_information(info.names, model, CONFIG, L)
    # mirror symmetry, up to the physics engine's asymmetric contact solver, which can
    # move the stick-slip transition by one interval of the 120 and so one interval of
    # the active set (information/observed.py): measured 1.6 %, allowed 3 %
    assert score(F[160], prior) == pytest.approx(score(F[20], prior), rel=0.03)
    past = prior + 5 * F[160]  # five left-face pokes already in the data
    for kind in ("logdet", "A", "D"):
        left = score(F[160], past, kind)
        assert left < score(F[20], past, kind), kind
        assert left < score(F[90], past, kind), kind
    # and the planner, asked twice (before and after), moves away from the known face
    from tacest.planning.actions import ActionSpace
    from tacest.planning.cem import cem_maximize
    from tacest.planning.planner import Scorer

    space = ActionSpace()
    lo, hi = space.bounds()
    sc = Scorer(info=info, model=model, I_past=past, kind="logdet")
    res = cem_maximize(lambda u: sc(space.action(0, u, model.centroid__world)), lo, hi,
                       np.random.default_rng(1), iterations=2, population=8)
    chosen = space.action(0, res.samples[res.best], model.centroid__world)
    pred = predict_poke(model, chosen)
    n_first = pred.normal__world[np.argmax(pred.contact[:, 0]), 0]
    # the face first touched is not the left one (outward normal (-1, 0)): 0.9 is cos 26°,
    # far from the next face's normal (0, 1) and the corner normals in between
    assert n_first[0] > -0.9, (math.degrees(chosen[1]), n_first)


def test_past_information_adds_the_prior_and_follows_names():
    model = _box_model()
    names = information_names_for(make_shape("box"))
    I_obs = np.diag(np.arange(1.0, len(names) + 1))
    shuffled = names[::-1]
    est = Estimate(dim=2, shape="box", vertices=model.vertices, params={}, runs=[],
                   information=I_obs[::-1, ::-1], info_names=shuffled)
    got = past_information(est, model, CONFIG, L, names)
    np.testing.assert_allclose(got, I_obs + prior_information(names, model, CONFIG, L))
    est.info_names = ["width", "height"]
    est.information = np.eye(2)
    with pytest.raises(TacestError, match="do not match"):
        past_information(est, model, CONFIG, L, names)


# ---------------------------------------------------------------------------------
# plan files and the CLI


def _sim_run(path, pokes=1, seed=3):
    from tacest.sim.record import SimOptions, record_sim

    run = record_sim(SimOptions(object_spec="box", seed=seed, pokes=pokes))
    write_run(run, path)
    return read_run(path)


def estimate_from_truth(run, scale=1.05, fail=False):
    """A stand-in estimate (no solve): the truth's box, 5 % too large, at the true poses,
    with a modest observed information."""
    if fail:
        raise SolveFailedError("IPOPT failed in stage 'homotopy 2/2': Maximum_Iterations_Exceeded")
    tr = run.truth
    w, h = np.ptp(tr.vertices[:, 0]), np.ptp(tr.vertices[:, 1])
    names = information_names_for(make_shape("box"))
    info = np.diag([1e6, 1e6, 1e2, 1.0, 1e2, 1e2, 1e6, 1e6, 1e3])
    pose = np.asarray(tr.pose, float)
    return Estimate(dim=2, shape="box", vertices=box_vertices(scale * w, scale * h),
                    params={"mass": tr.mass, "inertia": tr.inertia, "friction_ground": tr.friction_ground,
                            "friction_finger": tr.friction_finger},
                    runs=[RunEstimate(pose=pose, velocity=np.zeros_like(pose), source_file=str(run.filename or ""))],
                    solver_status="Solve_Succeeded", success=True, information=info, info_names=names,
                    config=CONFIG.to_dict())


def _tacest(*args, cwd=None):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, cwd=cwd)


def _one_error_line(res):
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tacest: error:"), res.stderr
    return lines[0]


def test_plan_cli_writes_a_plan_that_record_executes(tmp_path):
    run = _sim_run(tmp_path / "run.h5")
    write_estimate(estimate_from_truth(run), tmp_path / "est.h5")
    res = _tacest("plan", "est.h5", "run.h5", "--iterations", "2", "--population", "4", "--seed", "5",
                  "-o", "plan.h5", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    plan = read_plan(tmp_path / "plan.h5")
    assert (plan.method, plan.score, plan.kind) == ("eig", "logdet", "poke")
    assert plan.candidates.shape == (8, 6) and np.all(np.isfinite(plan.scores))
    assert plan.scores[np.all(plan.candidates == plan.chosen, 1)][0] == plan.scores.max()
    a = plan.chosen_dict()
    assert math.radians(10) <= a["approach_angle"] <= math.radians(170)
    np.testing.assert_allclose([a["target_x"], a["target_y"]], run.truth.pose[-1, :2])  # the estimate's centroid
    assert len(plan.estimate_sha256) == 64
    # the simulator executes it, appending to the run
    res = _tacest("record", "--source", "sim", "--plan", "plan.h5", "-o", "run.h5", "--quiet", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    longer = read_run(tmp_path / "run.h5")
    assert longer.n_samples > run.n_samples and len(longer.actions.segments) == 2
    np.testing.assert_allclose(longer.actions.params[-1], plan.chosen)
    # the other methods and scores, from a (stand-in) estimate of the longer run
    write_estimate(estimate_from_truth(longer), tmp_path / "est.h5")
    for extra in (["--method", "random"], ["--method", "identity", "--score", "E"], ["--score", "A", "--vary", "depth"]):
        res = _tacest("plan", "est.h5", "run.h5", "--iterations", "1", "--population", "3", "-o", "p2.h5", "--quiet",
                      *extra, cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        p2 = read_plan(tmp_path / "p2.h5")
        assert p2.method == extra[1] if extra[0] == "--method" else p2.score == extra[1]
    assert read_plan(tmp_path / "p2.h5").chosen_dict()["depth"] != pytest.approx(0.02)


def test_plan_cli_failures_exit_2_and_leave_no_plan(tmp_path):
    run = _sim_run(tmp_path / "run.h5")
    write_estimate(estimate_from_truth(run), tmp_path / "est.h5")
    (tmp_path / "old.h5").write_bytes(b"an earlier plan")
    other = _sim_run(tmp_path / "other.h5", pokes=2)
    assert other.n_samples != run.n_samples
    cases = [
        (["plan", "missing.h5", "run.h5", "-o", "old.h5"], "no such file"),
        (["plan", "est.h5", "other.h5", "-o", "old.h5"], "not the run the estimate was made from"),
        (["plan", "est.h5", "run.h5", "run.h5", "-o", "old.h5"], "same run"),
        (["plan", "est.h5", "run.h5", "other.h5", "-o", "old.h5"], "estimated from 1 run(s), 2 given"),
        (["plan", "est.h5", "run.h5", "--method", "oracle", "-o", "old.h5"], "oracle"),
        (["plan", "run.h5", "run.h5", "-o", "old.h5"], "attrs format"),
    ]
    for args, msg in cases:
        line = _one_error_line(_tacest(*args, cwd=tmp_path))
        assert msg in line, (args, line)
        assert (tmp_path / "old.h5").read_bytes() == b"an earlier plan"  # untouched
    line = _one_error_line(_tacest("plan", "est.h5", "run.h5", "--iterations", "1", "--population", "2",
                                   "-o", "nofolder/plan.h5", cwd=tmp_path))
    assert "does not exist" in line and not (tmp_path / "nofolder").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["est.h5", "old.h5", "other.h5", "run.h5"]


def test_explore_cli_failures_exit_2(tmp_path):
    (tmp_path / "taken").write_text("")
    for args, msg in [(["-o", "taken"], "is a file"), (["-o", "d", "--shape", "blob"], "unknown shape"),
                      (["-o", "d", "--policy", "oracle"], "oracle"), (["-o", "d", "--pokes", "0"], "pokes"),
                      (["-o", "d", "--object", "nothing.txt"], "nothing.txt")]:
        assert msg in _one_error_line(_tacest("explore", *args, cwd=tmp_path)), args


def test_explore_loop_files_and_summary(tmp_path, monkeypatch, caplog):
    """The loop's mechanics with a stand-in estimator (no solve): per-step files, the
    plan from the estimator's start guess after a failed estimate, summary.json and the
    learning curve."""
    import tacest.estimation.estimator as estimator
    from tacest.planning.explore import ExploreOptions, explore

    calls, previous = [], []

    def fake(runs, shape, config=None, **kw):
        calls.append(runs[0].n_samples)
        previous.append(kw.get("previous"))
        return estimate_from_truth(runs[0], fail=len(calls) == 2)

    monkeypatch.setattr(estimator, "estimate_2d", fake)
    out = tmp_path / "loop"
    with caplog.at_level(logging.INFO, logger="tacest.planning.explore"):
        summary = explore(ExploreOptions(object_spec="box", seed=2, policy="eig", pokes=3, iterations=1,
                                         population=3), out)
    lines = [r.getMessage() for r in caplog.records if r.name == "tacest.planning.explore"]
    names = sorted(p.name for p in out.iterdir())
    assert names == ["estimate_1.h5", "estimate_3.h5", "learning_curve.png", "plan_1.h5", "plan_2.h5", "run.h5",
                     "summary.json"]
    assert len(calls) == 3 and calls[0] < calls[1] < calls[2]  # the run grows by one poke per step
    run = read_run(out / "run.h5")
    assert run.truth is not None and len(run.actions.segments) == 3
    np.testing.assert_allclose(run.actions.params[1], read_plan(out / "plan_1.h5").chosen)
    np.testing.assert_allclose(run.actions.params[2], read_plan(out / "plan_2.h5").chosen)
    back = json.loads((out / "summary.json").read_text())
    assert back == json.loads(json.dumps(summary))
    steps = back["steps"]
    assert [s["pokes"] for s in steps] == [1, 2, 3]
    assert steps[0]["chamfer"] > 0 and steps[0]["mass_rel"] == pytest.approx(0.0, abs=1e-9)
    assert steps[1]["estimate_status"] == "failed" and steps[1]["chamfer"] is None
    assert "Maximum_Iterations_Exceeded" in steps[1]["estimate_error"]
    assert [s.get("planned_from") for s in steps] == ["estimate", "start guess", None]
    assert steps[0]["plan_time"] > 0 and "friction_ground_rel" in steps[2]
    assert len(lines) == 3 and lines[1].startswith("[2/3]")
    assert read_estimate(out / "estimate_3.h5").success
    # the last successful estimate is one more start of the next (step 2 failed: step 3
    # starts from step 1's too)
    assert previous[0] is None
    assert [Path(p.filename).name for p in previous[1:]] == ["estimate_1.h5", "estimate_1.h5"]


def test_explore_dynamic_style_pokes_fast_from_the_first_poke_on(tmp_path, monkeypatch):
    """tacest explore --poke-style dynamic: the first poke from the simulator's dynamic
    mix (0.1-0.6 m/s) and the planned ones fast, aimed at or above the centroid
    (stand-in estimator, as above)."""
    import tacest.estimation.estimator as estimator
    from tacest.planning.explore import ExploreOptions, explore
    from tacest.sim.pokes import POKE_NAMES

    monkeypatch.setattr(estimator, "estimate_2d", lambda runs, shape, config=None, **kw: estimate_from_truth(runs[0]))
    out = tmp_path / "loop"
    summary = explore(ExploreOptions(object_spec="box", seed=3, policy="eig", pokes=2, iterations=1, population=3,
                                     poke_style="dynamic"), out)
    assert summary["options"]["poke_style"] == "dynamic"
    run = read_run(out / "run.h5")
    speeds = run.actions.params[:, POKE_NAMES.index("speed")]
    assert np.all((speeds >= 0.1) & (speeds <= 0.6)), speeds
    plan = read_plan(out / "plan_1.h5").chosen_dict()
    pose = read_estimate(out / "estimate_1.h5").runs[-1].pose[-1]
    assert plan["target_y"] >= pose[1] - 1e-9


def test_the_dynamic_action_space_searches_speed_and_aim_height():
    """poke style dynamic: depth (2-12 cm), speed (0.1-0.6 m/s, the simulators' fast
    pokes) and the aim's height above the centroid (0-45 % of the object's height along
    the ground normal) are searched; gentle keeps the slow pokes at the centroid; height
    needs the object."""
    from tacest.errors import TacestError
    from tacest.planning.actions import DYNAMIC_DEPTH_RANGE, DYNAMIC_SPEED_RANGE, HEIGHT_RANGE, ActionSpace, ActionSpace3
    from tacest.sim.pokes import POKE_NAMES

    up = np.array([0.0, 1.0])
    space = ActionSpace(style="dynamic", object_height=0.1, up=up)
    assert space.names == ["approach_angle", "depth", "speed", "height"]
    lo, hi = space.bounds()
    np.testing.assert_allclose(lo[1:], [DYNAMIC_DEPTH_RANGE[0], DYNAMIC_SPEED_RANGE[0], HEIGHT_RANGE[0]])
    np.testing.assert_allclose(hi[1:], [DYNAMIC_DEPTH_RANGE[1], DYNAMIC_SPEED_RANGE[1], HEIGHT_RANGE[1]])
    a = dict(zip(POKE_NAMES, space.action(0, [1.0, 0.08, 0.4, 0.3], np.array([0.2, 0.05]))))
    assert a["speed"] == 0.4 and a["depth"] == 0.08 and a["target_x"] == 0.2
    assert a["target_y"] == pytest.approx(0.05 + 0.3 * 0.1)
    rng = np.random.default_rng(0)
    for _ in range(20):
        r = dict(zip(POKE_NAMES, space.random_action(rng, np.array([0.0, 0.05]))))
        assert DYNAMIC_SPEED_RANGE[0] <= r["speed"] <= DYNAMIC_SPEED_RANGE[1]
        assert 0.05 <= r["target_y"] <= 0.05 + HEIGHT_RANGE[1] * 0.1
    assert ActionSpace().names == ["approach_angle"]  # gentle: as before
    s3 = ActionSpace3(style="dynamic", object_height=0.08, up=np.array([0.0, 0.0, 1.0]))
    assert s3.names == ["approach_azimuth", "approach_elevation", "depth", "speed", "height"]
    with pytest.raises(TacestError, match="height"):
        ActionSpace(vary=("height",))
    with pytest.raises(TacestError, match="poke style"):
        ActionSpace(style="wild")


def test_plan_cli_dynamic_style_plans_a_fast_high_poke_that_record_executes(tmp_path):
    run = _sim_run(tmp_path / "run.h5")
    write_estimate(estimate_from_truth(run), tmp_path / "est.h5")
    res = _tacest("plan", "est.h5", "run.h5", "--poke-style", "dynamic", "--iterations", "1", "--population", "4",
                  "-o", "plan.h5", "--quiet", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    a = read_plan(tmp_path / "plan.h5").chosen_dict()
    assert 0.1 <= a["speed"] <= 0.6
    height = np.ptp(run.truth.vertices @ np.array([[np.cos(run.truth.pose[-1, 2]), np.sin(run.truth.pose[-1, 2])],
                                                    [-np.sin(run.truth.pose[-1, 2]), np.cos(run.truth.pose[-1, 2])]])[:, 1])
    assert 0.0 <= a["target_y"] - run.truth.pose[-1, 1] <= 0.45 * height + 1e-9
    res = _tacest("record", "--source", "sim", "--plan", "plan.h5", "-o", "run.h5", "--quiet", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    res = _tacest("plan", "est.h5", "run.h5", "--poke-style", "wild", "-o", "p.h5", cwd=tmp_path)
    assert res.returncode == 2 and not (tmp_path / "p.h5").exists()


def test_the_planner_keeps_a_bounded_number_of_information_models():
    """Each step of a closed loop has its estimate's scales in the key of its expected-
    information model: the planner's caches keep at most INFO_CACHE_LIMIT of them (an
    unbounded cache grows with the loop), and a model asked for again is the same object."""
    from tacest.estimation.config import EstimatorConfig
    from tacest.planning import planner as P

    cfg = EstimatorConfig()
    first = P.expected_information_model("box", 1, cfg, 0.1, 0.5)
    assert P.expected_information_model("box", 1, cfg, 0.1, 0.5) is first
    for i in range(P.INFO_CACHE_LIMIT + 2):
        P.expected_information_model("box", 1, cfg, 0.2 + 0.01 * i, 0.5)
    assert len(P._INFO_CACHE) == P.INFO_CACHE_LIMIT and P._INFO3_CACHE.limit == P.INFO_CACHE_LIMIT
    assert P.expected_information_model("box", 1, cfg, 0.1, 0.5) is not first  # dropped, built again

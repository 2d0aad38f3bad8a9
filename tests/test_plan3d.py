"""3-D planning: the expected information of a predicted poke (tacest.information.expected3d)
against finite differences, what it says about touched and untouched faces, and
`tacest plan` / `tacest explore` in the MuJoCo world.

The information cases use the true object of a short simulated recording (no IPOPT
solve); the command cases run one tiny loop (2 pokes, random policy) and plan from its
first estimate.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tacest.errors import TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import choose_scales
from tacest.estimation.estimator3d import effects_3d
from tacest.geometry.shapes3d import make_shape_3d
from tacest.geometry.transforms import quat_to_matrix
from tacest.information.expected3d import (ExpectedInformation3D, ModelState3, predict_poke_3d, prediction_run_3d,
                                           theta_of_estimate, twist_map)
from tacest.information.scores import score
from tacest.information.sensitivity import identity_sensitivity, information
from tacest.sim.record import SimOptions

TACEST = str(Path(sys.executable).parent / "tacest")
CONFIG = EstimatorConfig()
#: m, poke depth and m/s, speed of the test pokes (a 1 s approach, as the planner's default)
DEPTH, SPEED = 0.02, 0.04


@pytest.fixture(scope="module")
def truth_model():
    """(ModelState3 of the true box at the end of a 1-poke, 3-finger, no-force
    recording, its ExpectedInformation3D)."""
    from tacest.dims import record_sim

    run = record_sim(SimOptions(dim=3, object_spec="box", seed=1, pokes=1, fingers=3, force_stream=False))
    tr = run.truth
    shape = make_shape_3d("box")
    effects = effects_3d(shape, CONFIG)
    scales = choose_scales([run], CONFIG)
    params = {"mass": tr.mass, "friction_ground": tr.friction_ground, "friction_finger": tr.friction_finger}
    theta = theta_of_estimate(shape, effects, tr.vertices, params, tr.inertia, scales)
    model = ModelState3(shape=shape, effects=effects, scales=scales, theta=theta, vertices=np.asarray(tr.vertices),
                        mass=float(tr.mass), inertia=np.asarray(tr.inertia, float),
                        friction_ground=float(tr.friction_ground), friction_finger=float(tr.friction_finger),
                        pose=np.asarray(tr.pose[-1], float), p_finger__world=run.finger_position[-1].copy(),
                        finger_radius=run.finger_radius.copy(), dt=run.dt, has_force=False,
                        gravity=float(np.linalg.norm(run.gravity)), config=CONFIG)
    info = ExpectedInformation3D("box", 3, CONFIG, effects, scales)
    return model, info


def _face_azimuths(model) -> list:
    """rad: the approach azimuths straight onto the box's two horizontal body axes'
    +faces (the two body axes closest to horizontal)."""
    R = quat_to_matrix(model.pose[3:])
    axes = np.argsort(np.abs(R[2]))[:2]
    return [math.atan2(R[1, k], R[0, k]) for k in axes]


def _poke(model, azimuth, elevation=math.radians(20.0), finger=0):
    return np.array([finger, azimuth, elevation, *model.centroid__world, DEPTH, SPEED])


def _twisted(pose, delta):
    """pose (7,) moved by the body-frame twist delta (6,) = (δp_b m, δr_b rad)."""
    from tacest.geometry.transforms import quat_multiply

    q = pose[3:]
    R = quat_to_matrix(q)
    ang = float(np.linalg.norm(delta[3:]))
    axis = delta[3:] / ang if ang > 0 else np.zeros(3)
    dq = np.r_[math.cos(ang / 2), math.sin(ang / 2) * axis]
    return np.r_[pose[:3] + R @ delta[:3], quat_multiply(q, dq)]


def test_information_of_a_poke_against_finite_differences(truth_model):
    """The linearized residuals of a predicted poke against central differences of the
    estimator's residuals: every kept column (θ, the start pose's twist), the nuisance
    columns along random directions, and the identity-Jacobian information
    G_idᵀG_id built from differences (θ, and every pose moved rigidly by one twist)."""
    model, info = truth_model
    pred = predict_poke_3d(model, _poke(model, _face_azimuths(model)[0]))
    assert pred.contact[:, 0].any(), "the test poke must touch the box"
    run = prediction_run_3d(pred, model)
    lin = info.prediction(model, pred)
    U, LF = lin.extra["U"], lin.extra["LF"]

    def residuals(theta=None, poses=None):
        return info.linearize(model.theta if theta is None else theta, run, pred.pose if poses is None else poses,
                              LF, U=U, keep=0).r

    # central differences: truncation O(h²) ~1e-8 of the curvature, rounding ~1e-16/h;
    # h = 1e-5 (scaled θ ~1, twist m and rad) balances them; columns agree to 1e-4 of
    # their own size (the contact-flag and normal terms are smooth at this scale)
    h = 1e-5
    nt = info.n_theta
    fd = np.zeros_like(lin.Ja)
    for j in range(nt):
        e = np.zeros(nt)
        e[j] = h
        fd[:, j] = (residuals(theta=model.theta + e) - residuals(theta=model.theta - e)) / (2 * h)
    for j in range(6):
        d = np.zeros(6)
        d[j] = h
        plus, minus = pred.pose.copy(), pred.pose.copy()
        plus[0], minus[0] = _twisted(pred.pose[0], d), _twisted(pred.pose[0], -d)
        fd[:, nt + j] = (residuals(poses=plus) - residuals(poses=minus)) / (2 * h)
    scale = np.maximum(np.linalg.norm(lin.Ja, axis=0), 1e-6)
    assert np.all(np.linalg.norm(fd - lin.Ja, axis=0) <= 1e-4 * scale + 1e-6)

    rng = np.random.default_rng(0)
    for _ in range(3):
        dx = rng.standard_normal(lin.n_x) * 1e-2
        got = (lin.residual_at(h * dx) - lin.residual_at(-h * dx)) / (2 * h)
        want = lin.Jx @ dx
        assert np.linalg.norm(got - want) <= 1e-4 * np.linalg.norm(want) + 1e-6

    # the identity-Jacobian sensitivity from differences: θ columns, and every pose of
    # the poke moved rigidly by the same body-frame twist (∂x/∂s = S_identity)
    m = np.asarray(lin.measured, bool)
    G_fd = np.zeros((int(m.sum()), nt + 6))
    G_fd[:, :nt] = fd[m, :nt]
    for j in range(6):
        d = np.zeros(6)
        d[j] = h
        plus = np.array([_twisted(p, d) for p in pred.pose])
        minus = np.array([_twisted(p, -d) for p in pred.pose])
        G_fd[:, nt + j] = ((residuals(poses=plus) - residuals(poses=minus)) / (2 * h))[m]
    G = identity_sensitivity(lin)
    F, F_fd = G.T @ G, G_fd.T @ G_fd
    assert np.linalg.norm(F - F_fd) <= 1e-3 * np.linalg.norm(F)
    np.testing.assert_allclose(info.to_physical(information(lin, "identity"), model), info.to_physical(F, model),
                               rtol=1e-9, atol=1e-9 * np.abs(F).max())


def test_a_squeeze_of_two_fingers_informs_more_than_one_of_its_pokes(truth_model):
    """An action of two fingers (tacest.sim3d.pokes.action_names(2)) pressing an untouched
    face and the face opposite it, together: both fingers touch in the prediction, and
    it scores above the single poke at that face (it feels both faces: the box's width
    along that axis), after a past that knows another face."""
    model, info = truth_model
    az_known, az_new = _face_azimuths(model)
    F_known = info.information(model, predict_poke_3d(model, _poke(model, az_known)), "identity")
    I_past = info.prior_information(model) + F_known
    one = _poke(model, az_new)
    pred_two = predict_poke_3d(model, np.r_[one, _poke(model, az_new + math.pi, finger=1)])
    assert pred_two.contact[:, 0].any() and pred_two.contact[:, 1].any() and len(pred_two.action) == 16
    s_one = score(info.information(model, predict_poke_3d(model, one), "identity"), I_past)
    s_two = score(info.information(model, pred_two, "identity"), I_past)
    assert s_two > s_one, (s_two, s_one)


def test_the_3d_action_space_of_several_fingers():
    """ActionSpace3 with fingers_per_action = 2: the searched coordinates and bounds are
    one finger's, twice (names suffixed .1); an action takes the finger nearest each
    direction, a second one never the first's; random actions move two distinct
    fingers; 2-D and more fingers than the model has are one clear error each."""
    from tacest.planning.actions import ActionSpace, ActionSpace3, split_action
    from tacest.sim3d.pokes import action_names, pokes_from_vector

    fingers = np.array([[0.2, 0.0, 0.05], [-0.2, 0.0, 0.05], [0.0, 0.2, 0.05]])
    sp = ActionSpace3(n_fingers=3, p_finger__world=fingers, fingers_per_action=2, vary=("depth",))
    one = ActionSpace3(n_fingers=3, p_finger__world=fingers, vary=("depth",))
    assert sp.names == one.names + [f"{n}.1" for n in one.names]
    lo, hi = sp.bounds()
    assert np.array_equal(lo, np.tile(one.bounds()[0], 2)) and np.array_equal(hi, np.tile(one.bounds()[1], 2))
    # both directions from +x: the first takes finger 0 (at +x), the second the next nearest
    a = sp.action(None, [0.0, 0.3, 0.02, 0.1, 0.3, 0.03], np.zeros(3))
    pokes = pokes_from_vector(a, 3, sp.poke_names)
    assert sp.poke_names == action_names(2) and [p.finger for p in pokes][0] == 0 and pokes[1].finger != 0
    assert [p.depth for p in pokes] == [0.02, 0.03]
    d = dict(zip(sp.poke_names, a))
    assert [x["finger"] for x in split_action(d)] == [p.finger for p in pokes]
    rng = np.random.default_rng(3)
    for _ in range(5):
        r = pokes_from_vector(sp.random_action(rng, np.zeros(3)), 3)
        assert len({p.finger for p in r}) == 2
    with pytest.raises(TacestError, match="fingers-per-action"):
        ActionSpace3(n_fingers=1, p_finger__world=fingers[:1], fingers_per_action=2)
    from tacest.planning.actions import action_space_for

    class Flat:  # a 2-D planning model state's shape of things
        n_fingers, up, vertices, pose = 2, np.array([0.0, 1.0]), np.array([[0.0, 0.0], [0.1, 0.05]]), np.zeros(3)

    assert isinstance(action_space_for(Flat()), ActionSpace)
    with pytest.raises(TacestError, match="3-D only"):
        action_space_for(Flat(), fingers_per_action=2)


def test_twist_map_against_finite_differences():
    """twist_map: d[p / L, q] / d(δp_b, δr_b) against central differences of _twisted."""
    q = np.array([0.9, 0.1, -0.3, 0.2])
    pose = np.r_[0.1, -0.2, 0.05, q / np.linalg.norm(q)]
    L, h = 0.1, 1e-6
    E = twist_map(pose[3:], L)
    for j in range(6):
        d = np.zeros(6)
        d[j] = h
        diff = (_twisted(pose, d) - _twisted(pose, -d)) / (2 * h)
        np.testing.assert_allclose(np.r_[diff[:3] / L, diff[3:]], E[:, j], atol=1e-8)


@pytest.mark.parametrize("method", ["identity", "marginal"])
def test_a_poke_at_a_known_face_scores_lower(truth_model, method):
    """After a poke at one face (the past: the prior and that poke's information), the
    same poke again scores lower than a poke at an untouched face."""
    model, info = truth_model
    az_known, az_new = _face_azimuths(model)
    F_known = info.information(model, predict_poke_3d(model, _poke(model, az_known)), method)
    F_new = info.information(model, predict_poke_3d(model, _poke(model, az_new)), method)
    I_past = info.prior_information(model) + F_known
    s_known, s_new = score(F_known, I_past), score(F_new, I_past)
    assert s_known < s_new, (s_known, s_new)
    # by a wide margin (measured 6-15x): the poke at the known face repeats what the
    # past holds, and before that poke it was worth as much as the other (measured
    # within 10 %: the box is nearly a cube)
    s0_known = score(F_known, info.prior_information(model))
    assert 3 * s_known < s_new and s_known < 0.2 * s0_known


@pytest.fixture(scope="module")
def loop_dir(tmp_path_factory):
    """A 2-poke random loop in the MuJoCo world (3 fingers, contact and normal only)."""
    out = tmp_path_factory.mktemp("explore3d") / "loop"
    res = subprocess.run([TACEST, "explore", "--dim", "3", "--fingers", "3", "--object", "box", "--seed", "1",
                          "--policy", "random", "--pokes", "2", "-o", str(out)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    return out, res


@pytest.mark.slow
def test_explore_3d_writes_the_2d_layout_and_views(loop_dir):
    out, res = loop_dir
    for name in ("run.h5", "estimate_1.h5", "estimate_2.h5", "plan_1.h5", "summary.json", "learning_curve.png",
                 "view_3d.png", "view_3d.html"):
        assert (out / name).exists(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dim"] == 3 and summary["fingers"] == 3 and summary["force"] is False
    assert [s["pokes"] for s in summary["steps"]] == [1, 2]
    assert all(s["chamfer"] is not None and s["chamfer"] > 0 for s in summary["steps"])
    assert "2/2" in res.stderr and " left" in res.stderr  # the progress bar, with the time left (an ETA)
    from tacest.io.run import read_run

    run = read_run(out / "run.h5")
    assert run.dim == 3 and run.truth is not None and not run.has_force and run.n_fingers == 3
    import h5py

    # the second estimate had the first one as one more start (estimator3d.previous_start)
    starts = []
    for n in (1, 2):
        with h5py.File(out / f"estimate_{n}.h5", "r") as f:
            starts.append([a["start"] for a in json.loads(f.attrs["starts"])])
    assert "previous estimate" not in starts[0] and starts[1][0] == "previous estimate"


@pytest.fixture(scope="module")
def estimate_1(tmp_path_factory):
    """(estimate, run) paths: a 1-poke, 3-finger, no-force recording and its estimate."""
    d = tmp_path_factory.mktemp("plan3d")
    run, est = d / "run.h5", d / "est.h5"
    for args in (["record", "--source", "sim", "--dim", "3", "--fingers", "3", "--no-force", "--pokes", "1",
                  "--seed", "1", "-o", str(run)], ["estimate", str(run), "--quiet", "-o", str(est)]):
        res = subprocess.run([TACEST, *args], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
    return est, run


def test_the_planning_model_of_an_estimate_with_restitution_leaves_it_out(estimate_1):
    """ModelState3.from_estimate: an estimate made with restitution (whose stage looks
    back five poses) is planned with the rest of its model; restitution's e is not
    needed in /params and the planning model equals the one without it."""
    from tacest.io.estimate import read_estimate
    from tacest.io.run import read_run

    est_path, run_path = estimate_1
    est, run = read_estimate(est_path), read_run(run_path)
    plain = ModelState3.from_estimate(est, [run], EstimatorConfig())
    est.model = [*est.model, "restitution"] if est.model else [*plain.effects, "restitution"]
    with_law = ModelState3.from_estimate(est, [run], EstimatorConfig())
    assert "restitution" not in with_law.effects and with_law.effects == plain.effects
    assert np.array_equal(with_law.theta, plain.theta)


def test_a_plan_of_two_fingers_is_recorded_as_one_action(estimate_1, tmp_path):
    """`tacest plan --fingers-per-action 2`: candidates are actions of two distinct
    fingers' pokes (names tacest.sim3d.pokes.action_names(2)), the message names both;
    `tacest record --plan` appends them as two rows of one segment; in 2-D, or with more
    fingers than the run has, one line and exit 2."""
    from tacest.io.plan import read_plan
    from tacest.io.run import read_run
    from tacest.sim3d.pokes import action_names, pokes_from_vector

    est, run = (str(p) for p in estimate_1)
    plan_path = tmp_path / "two.h5"
    res = subprocess.run([TACEST, "plan", est, run, "--fingers-per-action", "2", "--iterations", "1",
                          "--population", "3", "-o", str(plan_path)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    plan = read_plan(plan_path)
    assert list(plan.names) == list(action_names(2)) and plan.candidates.shape == (3, 16)
    for c in plan.candidates:
        assert len({p.finger for p in pokes_from_vector(c, 3, plan.names)}) == 2
    assert res.stderr.count("finger ") >= 2 and "; finger" in res.stderr
    appended = tmp_path / "run.h5"
    appended.write_bytes(Path(run).read_bytes())
    res = subprocess.run([TACEST, "record", "--source", "sim", "--dim", "3", "--fingers", "3", "--no-force",
                          "--plan", str(plan_path), "-o", str(appended)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    seg = read_run(appended).actions.segments
    assert len(seg) == 3 and np.array_equal(seg[1], seg[2]) and seg[1, 0] == seg[0, 1]
    for args in (["explore", "--fingers-per-action", "2", "--fingers", "2", "--pokes", "1"],
                 ["explore", "--dim", "3", "--fingers", "1", "--fingers-per-action", "2", "--pokes", "1"]):
        res = subprocess.run([TACEST, *args, "-o", str(tmp_path / "loop")], capture_output=True, text=True)
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and "fingers" in res.stderr, res.stderr


def test_plan_3d_cli(estimate_1, tmp_path):
    """`tacest plan` on a 3-D estimate: eig with the identity and marginal information,
    3-D poke vectors aimed at the estimated centroid; `tacest record --plan` executes it;
    bad combinations are one line and exit 2."""
    from tacest.io.plan import read_plan
    from tacest.sim3d.pokes import POKE3_NAMES

    est, run = (str(p) for p in estimate_1)
    for info in ("identity", "marginal"):
        plan_path = tmp_path / f"plan_{info}.h5"
        res = subprocess.run([TACEST, "plan", est, run, "--information", info, "--iterations", "1", "--population",
                              "3", "-o", str(plan_path)], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
        plan = read_plan(plan_path)
        assert list(plan.names) == list(POKE3_NAMES) and plan.candidates.shape == (3, 8)
        assert json.loads(plan.extra_attrs["planner"])["information"] == info
        assert plan.scores.max() == plan.scores[np.all(plan.candidates == plan.chosen, 1)][0]
    appended = tmp_path / "appended.h5"
    appended.write_bytes(Path(run).read_bytes())
    rec = subprocess.run([TACEST, "record", "--source", "sim", "--dim", "3", "--fingers", "3", "--no-force",
                          "--plan", str(tmp_path / "plan_marginal.h5"), "-o", str(appended)],
                         capture_output=True, text=True)
    assert rec.returncode == 0, rec.stderr
    bad = subprocess.run([TACEST, "plan", est, str(appended), "-o", str(tmp_path / "p.h5")],
                         capture_output=True, text=True)  # not the run the estimate was made from
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
    bad = subprocess.run([TACEST, "plan", est, run, "--method", "identity", "--information", "marginal", "-o",
                          str(tmp_path / "p.h5")], capture_output=True, text=True)
    assert bad.returncode == 2 and "goes with method eig" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_estimate_starts_from_an_earlier_estimate(loop_dir, tmp_path):
    """``tacest estimate --start-from``: the loop's first estimate (first poke) is one more
    start of an estimate of both pokes, solved first; a mismatched or missing earlier
    estimate is one line and exit 2, before any solve, and leaves no output."""
    import h5py

    out, _ = loop_dir
    run, first = str(out / "run.h5"), str(out / "estimate_1.h5")
    res = subprocess.run([TACEST, "estimate", run, "--start-from", first, "--quiet", "-o", str(tmp_path / "e.h5")],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    with h5py.File(tmp_path / "e.h5", "r") as f:
        starts = [a["start"] for a in json.loads(f.attrs["starts"])]
    assert starts[0] == "previous estimate" and len(starts) > 1
    for args, message in (([run, "--shape", "polytope:8", "--start-from", first], "not a 3-D polytope:8"),
                          ([run, "--start-from", str(tmp_path / "missing.h5")], "missing.h5"),
                          ([run, "--method", "shooting", "--start-from", first], "implicit estimators only")):
        bad = subprocess.run([TACEST, "estimate", *args, "-o", str(tmp_path / "bad.h5")], capture_output=True,
                             text=True)
        assert bad.returncode == 2 and message in bad.stderr, bad.stderr
        assert len(bad.stderr.strip().splitlines()) == 1 and not (tmp_path / "bad.h5").exists()


@pytest.mark.parametrize("args, message", [
    (["--dim", "3", "--object", "nonsense"], "nonsense"),
    (["--dim", "3", "--policy", "identity", "--information", "marginal"], "goes with method eig"),
    (["--dim", "3", "--shape", "polygon:8"], "polygon"),
])
def test_explore_3d_bad_input_is_one_line_exit_2(tmp_path, args, message):
    res = subprocess.run([TACEST, "explore", *args, "--pokes", "2", "-o", str(tmp_path / "out")], capture_output=True,
                         text=True)
    assert res.returncode == 2, res.stderr
    assert message in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert not (tmp_path / "out" / "run.h5").exists()


def test_a_failed_3d_estimate_is_planned_from_the_start_guess(estimate_1):
    """The loop's fallback when a 3-D estimate fails: the estimator's initial guess as an
    Estimate (status "start guess", no information) that the planner can aim with."""
    from tacest.io.run import read_run
    from tacest.planning.explore import start_guess_estimate
    from tacest.planning.planner import PlanSettings, plan_next

    run = read_run(estimate_1[1])
    est = start_guess_estimate([run], "box", CONFIG)
    assert est.dim == 3 and est.solver_status == "start guess" and est.information is None
    assert est.runs[0].pose.shape == (run.n_samples, 7) and np.all(np.isfinite(est.runs[0].pose))
    plan = plan_next(est, [run], PlanSettings(method="identity", iterations=1, population=3))
    assert plan.candidates.shape == (3, 8) and np.all(np.isfinite(plan.scores))


def test_one_search_pokes_each_direction_with_the_nearest_finger():
    """ActionSpace3 with the fingertips known: one search, and a direction is poked by
    the finger nearest its approach; the poke vector is POKE3_NAMES'."""
    from tacest.planning.actions import ActionSpace3
    from tacest.sim3d.pokes import POKE3_NAMES

    tips = np.array([[0.2, 0.0, 0.1], [-0.2, 0.0, 0.1], [0.0, 0.2, 0.1]])
    space = ActionSpace3(n_fingers=3, p_finger__world=tips)
    assert space.searched_fingers() == [None] and ActionSpace3(n_fingers=3).searched_fingers() == [0, 1, 2]
    target = np.array([0.0, 0.0, 0.03])
    for az, finger in ((0.0, 0), (math.pi, 1), (math.pi / 2, 2)):
        a = dict(zip(POKE3_NAMES, space.action(None, [az, 0.3], target)))
        assert a["finger"] == finger and a["approach_azimuth"] == az and a["target_z"] == 0.03
    lo, hi = space.bounds()
    np.testing.assert_allclose([lo, hi], [[-math.pi, math.radians(10)], [math.pi, math.radians(90)]])


@pytest.mark.parametrize("faces", [None, [0.9, 0.1, 0.5, 0.3, 0.7, 0.2]])
def test_a_prediction_from_the_kept_settled_world_is_the_fresh_one_bit_for_bit(truth_model, faces):
    """predict_poke_3d keeps the settled world of a model (settled_world) and returns to
    its snapshot for every later poke: a poke predicted after another one is, bit for bit,
    the poke predicted on a fresh copy of the model (a world built and settled anew);
    also with face_friction, whose ground friction the stepping changes in the model."""
    import dataclasses

    from tacest.sim.effects import Effect

    model, _ = truth_model
    effects = [] if faces is None else [Effect(name="face_friction", params={"values": faces})]
    az = _face_azimuths(model)
    first = predict_poke_3d(dataclasses.replace(model), _poke(model, az[0]), effects=effects)
    kept = dataclasses.replace(model)  # no kept worlds (init=False field)
    assert kept.worlds == {}
    predict_poke_3d(kept, _poke(model, az[1], finger=1), effects=effects)  # another poke first: the world moved
    again = predict_poke_3d(kept, _poke(model, az[0]), effects=effects)
    assert len(kept.worlds) == 1
    for name in ("pose", "p_finger__world", "contact", "impulse__world"):
        assert np.array_equal(getattr(first, name), getattr(again, name)), name
    assert np.array_equal(np.isnan(first.normal__world), np.isnan(again.normal__world))
    assert np.array_equal(np.nan_to_num(first.normal__world), np.nan_to_num(again.normal__world))


def test_the_residuals_at_many_states_in_one_call_are_the_residuals_at_each(truth_model):
    """Linearized.residual_at of an (n_x, n) block of nuisance moves (one mapped call)
    equals residual_at column by column."""
    model, info = truth_model
    lin = info.prediction(model, predict_poke_3d(model, _poke(model, _face_azimuths(model)[0])))
    dX = np.random.default_rng(3).standard_normal((lin.n_x, 3)) * 1e-3
    many = lin.residual_at(dX)
    assert many.shape == (len(lin.r), 3)
    for i in range(3):
        np.testing.assert_array_equal(many[:, i], lin.residual_at(dX[:, i]))


#: the worker comparison, run in a fresh interpreter: a test process may hold threads
#: (of earlier tests), where tacest.parallel.fork_processes rightly refuses to fork
_WORKERS_SCRIPT = """
import sys
import numpy as np
from tacest.io.estimate import read_estimate
from tacest.io.run import read_run
from tacest.parallel import fork_processes
from tacest.planning.planner import PlanSettings, plan_next

est, run = read_estimate(sys.argv[1]), read_run(sys.argv[2])
assert fork_processes(2, 4) == 2, "a fresh process on Linux must fork"
plans = [plan_next(est, [run], PlanSettings(iterations=2, population=4, workers=w)) for w in (1, 2)]
same = np.array_equal(plans[0].candidates, plans[1].candidates) and np.array_equal(plans[0].scores, plans[1].scores)
print(same, [int(p.extra_attrs["evaluations"]) for p in plans], len(plans[0].scores))
"""


def test_a_3d_plan_is_the_same_for_any_number_of_worker_processes(estimate_1):
    """The candidates of a 3-D search scored by two forked processes give the plan that
    one process gives (every candidate's score does not depend on where it is computed)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the planner forks its workers on Linux only")
    res = subprocess.run([sys.executable, "-c", _WORKERS_SCRIPT, str(estimate_1[0]), str(estimate_1[1])],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split("\n")[0] == "True [8, 8] 8", res.stdout


def test_an_action_in_words_short_and_detailed():
    """describe_action: the loop's short line and `tacest plan`'s detailed one, each
    finger of a two-finger action once, in order; a 2-D poke by its approach angle."""
    from tacest.planning.actions import describe_action

    poke = {"finger": 1.0, "approach_azimuth": math.radians(40.0), "approach_elevation": math.radians(30.0),
            "target_x": 0.01, "target_y": 0.0, "target_z": 0.03, "depth": 0.02, "speed": 0.04}
    two = {**poke, **{f"{k}.1": v for k, v in poke.items()}, "finger.1": 2.0}
    assert describe_action(two) == "finger 1 from azimuth 40 deg, elevation 30 deg + finger 2 from azimuth 40 deg, " \
                                   "elevation 30 deg"
    long = describe_action(two, detailed=True).split("; ")
    assert [p.split(",")[0] for p in long] == ["finger 1", "finger 2"]
    assert long[0] == "finger 1, approach azimuth 40.0 deg, elevation 30.0 deg toward (0.0100, 0.0000, 0.0300) m, " \
                      "depth 20 mm, speed 40 mm/s"
    flat = {"finger": 0.0, "approach_angle": math.radians(35.0), "target_x": 0.0, "target_y": 0.0, "depth": 0.02,
            "speed": 0.04}
    assert describe_action(flat) == "approach 35 deg"

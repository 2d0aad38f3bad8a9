"""The 3-D estimator: quaternion kinematics, inertia validity, the box signed distance,
exact derivatives, a known answer from synthetic tosses, failure paths and 3-D eval."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from tacest.dynamics.rigid3d import (cholesky_from_inertia, inertia_numeric, qexp_half, qmul, quat_log_rate)
from tacest.errors import TacestError
from tacest.model.stage3d import body_rate
from tacest.geometry.polytope import box_vertices_3d, polytope_inertia
from tacest.geometry.shapes3d import Box3D, box_signed_distance, shape_sd_and_normal_function
from tacest.geometry.transforms import quat_angle, quat_from_axis_angle, quat_multiply
from tacest.io.run import Run, write_run

TACEST = str(Path(sys.executable).parent / "tacest")

#: the synthetic object: a box of distinct extents (m), uniform density, friction
EXTENTS = np.array([0.08, 0.10, 0.12])
MASS = 0.4
FRICTION = 0.3


def _dm(x):
    return np.asarray(ca.DM(x)).ravel()


# ---------------------------------------------------------------------------------
# quaternion kinematics


def test_constant_body_rate_integrates_to_the_closed_form_rotation():
    w = np.array([0.3, -1.2, 2.0])  # rad/s, body frame
    dt, n = 0.01, 300
    q0 = quat_from_axis_angle(np.array([1.0, 2.0, -0.5]), 0.7)
    q = ca.DM(q0)
    e = qexp_half(ca.DM(w), dt)
    norms = []
    for _ in range(n):
        q = qmul(q, e)
        norms.append(float(ca.norm_2(q)))
    # closed form: a constant body rate turns the body by |w| n dt about w (body axis)
    expected = quat_multiply(q0, quat_from_axis_angle(w, np.linalg.norm(w) * n * dt))
    # 1e-9 rad: the series of exp is exact to ~1e-16 per step at |w| dt = 0.02, so
    # what remains is float round-off accumulated over 300 products
    assert quat_angle(_dm(q), expected) < 1e-9
    # the update is normalised: unit norm kept to round-off over all steps
    assert max(abs(np.array(norms) - 1.0)) < 1e-12


def test_body_rate_inverts_the_update_and_is_smooth_at_rest():
    dt = 0.0068
    q0 = quat_from_axis_angle(np.array([0.2, -1.0, 0.4]), 1.1)
    for w in (np.array([3.0, -20.0, 7.0]), np.array([1e-9, 0.0, -2e-9]), np.zeros(3)):
        q1 = _dm(qmul(ca.DM(q0), qexp_half(ca.DM(w), dt)))
        # 1e-7 relative (plus 1e-12 rad/s): the asin series is accurate to < 1e-8 for
        # rotations below 0.5 rad per sample (here 0.15 rad at most)
        np.testing.assert_allclose(_dm(body_rate(ca.DM(q0), ca.DM(q1), dt)), w, rtol=1e-7, atol=1e-12)
        # the same body rate for -q (q and -q are one rotation) and for a scaled q
        np.testing.assert_allclose(_dm(body_rate(ca.DM(q0), ca.DM(-3.0 * q1), dt)), w, rtol=1e-7, atol=1e-12)
        np.testing.assert_allclose(quat_log_rate(q0, q1, dt), w, rtol=1e-7, atol=1e-12)
    # derivatives are finite at zero rate (the series has no 0/0)
    a, b = ca.SX.sym("a", 4), ca.SX.sym("b", 4)
    J = ca.Function("J", [a, b], [ca.jacobian(body_rate(a, b, dt), ca.vertcat(a, b))])
    assert np.all(np.isfinite(np.asarray(J(q0, q0))))


# ---------------------------------------------------------------------------------
# inertia


def test_every_inertia_parameter_gives_a_physical_inertia_and_round_trips():
    rng = np.random.default_rng(0)
    for c in rng.normal(scale=1.5, size=(300, 6)):
        I = inertia_numeric(c)
        ev = np.linalg.eigvalsh(I)
        assert ev[0] > 0
        # triangle inequalities of the principal moments (strict, relative 1e-12)
        assert ev[0] + ev[1] > ev[2] * (1 - 1e-12)
        np.testing.assert_allclose(I, I.T, atol=0)
        # 1e-8: the round trip goes through a Cholesky factorisation (condition numbers
        # up to ~1e6 for parameters 3 sigma out)
        np.testing.assert_allclose(cholesky_from_inertia(I), c, atol=1e-8 * max(1.0, np.abs(c).max()))
    box = polytope_inertia(box_vertices_3d(EXTENTS), MASS) / MASS
    np.testing.assert_allclose(inertia_numeric(cholesky_from_inertia(box)), box, rtol=1e-12)


def test_an_unphysical_inertia_is_refused():
    with pytest.raises(TacestError, match="not physically valid"):
        cholesky_from_inertia(np.diag([1.0, 1.0, 3.0]))  # 1 + 1 < 3


# ---------------------------------------------------------------------------------
# signed distance


@pytest.mark.parametrize("point,sd", [
    ((0.0, 0.0, 0.0), -0.05),            # centre: nearest face at 0.05
    ((0.07, 0.0, 0.0), 0.02),            # outside the x face
    ((0.0, -0.12, 0.01), 0.02),          # outside the -y face
    ((0.08, 0.14, 0.15), 0.05),          # beyond an edge: hypot(0.03, 0.04)
    ((0.09, 0.13, 0.17), np.sqrt(0.04 ** 2 + 0.03 ** 2 + 0.02 ** 2)),  # beyond a corner
    ((0.03, 0.0, 0.1), -0.02),           # inside, nearest the x face
    ((0.05, 0.02, 0.01), 0.0),           # on the x face
])
def test_box_signed_distance_hand_table(point, sd):
    half = np.array([0.05, 0.10, 0.15])
    value = float(ca.DM(box_signed_distance(ca.DM(point), ca.DM(half))))
    assert value == pytest.approx(sd, abs=1e-12)


def test_box_normal_is_the_gradient():
    fun = shape_sd_and_normal_function(Box3D())
    s, L = np.array([1.0, 2.0, 3.0]), 0.1  # extents 0.1, 0.2, 0.3 m
    for p, n in (((0.07, 0.0, 0.0), (1, 0, 0)), ((0.0, -0.11, 0.02), (0, -1, 0)),
                 ((0.08, 0.14, 0.0), (0.6, 0.8, 0))):
        _, nb = fun(p, s, L)
        np.testing.assert_allclose(_dm(nb), n, atol=1e-12)


# ---------------------------------------------------------------------------------
# synthetic tosses


@pytest.fixture(scope="module")
def tosses():
    """Two noiseless tosses of the box, simulated by the project's own 3-D model."""
    return _augmented_tosses()


def _assert_derivatives_match_finite_differences(est, seed=3):
    """Residual Jacobian, gradient and exact Hessian of est's NLP against central
    differences at a generic point near its start; returns the Jacobian J."""
    pr = est.problem
    rng = np.random.default_rng(seed)
    p = est.params(0.5, 1.0, 1.0, ridge=0.0)
    z = est.ground_impulses_nnls(est.initial_guess(), p)
    # perturbation 0.01 (scaled units): inside the smooth regions, off symmetric values;
    # the impulse variables u are moved into the linear part of the softplus
    z = z + rng.normal(size=pr.n_z) * 0.01
    z[pr.u_offset: pr.lf_offset] = 0.3 + rng.uniform(size=pr.lf_offset - pr.u_offset)
    r_fun = ca.Function("r", [pr.z_sym, pr.p_sym], [pr.residual_jacobian(pr.z_sym, pr.p_sym)[0]])
    f_fun = ca.Function("f", [pr.z_sym, pr.p_sym], [pr.f, ca.gradient(pr.f, pr.z_sym)])
    r0, J = (np.asarray(a.full() if hasattr(a, "full") else a) for a in pr.residual_jacobian(z, p))
    grad = _dm(f_fun(z, p)[1])
    H = pr.hess_lag["exact"](z, p, 1.0, np.zeros(0)).full()
    H = np.triu(H) + np.triu(H, 1).T
    Hgn = pr.hess_lag["gauss-newton"](z, p, 1.0, np.zeros(0)).full()
    h = 1e-6  # central differences: truncation ~h² · (third derivative), round-off ~1e-16 / h
    Jfd, Hfd = np.zeros_like(J), np.zeros_like(H)
    for k in range(pr.n_z):
        e = np.zeros(pr.n_z)
        e[k] = h
        Jfd[:, k] = (_dm(r_fun(z + e, p)) - _dm(r_fun(z - e, p))) / (2 * h)
        Hfd[:, k] = (_dm(f_fun(z + e, p)[1]) - _dm(f_fun(z - e, p)[1])) / (2 * h)
    # relative 1e-6 of the largest entry: the whitened residuals reach 1e4 per unit of the
    # scaled variables, so round-off in the differences is ~1e-10 · 1e4 / 1e-6
    assert np.abs(J - Jfd).max() <= 1e-6 * np.abs(J).max()
    np.testing.assert_allclose(grad, J.T @ _dm(r0), rtol=1e-9, atol=1e-9 * np.abs(grad).max())
    assert np.abs(H - Hfd).max() <= 1e-6 * np.abs(Hfd).max()
    # the Gauss–Newton model is exactly Jᵀ J (ridge 0), upper triangle
    np.testing.assert_allclose(Hgn, np.triu(J.T @ J), atol=1e-9 * np.abs(Hgn).max())
    return J


def test_derivatives_match_finite_differences(tosses, monkeypatch):
    """Residual Jacobian, gradient and exact Hessian of the 3-D NLP against central
    differences, at a generic point near the start (the virtual-machine functions; the
    compiled kernels are generated from the same expressions)."""
    monkeypatch.setenv("TACEST_NO_COMPILE", "1")
    from tacest.estimation.estimator3d import Estimator3D

    run = tosses[0]
    # the last 8 samples: the box on the ground, so that the contact terms are live
    short = run.replace(time=run.time[-8:] - run.time[-8], pose_obs=run.pose_obs[-8:], truth=None)
    from tacest.estimation.config import load_config

    # both 3-D effects in the model (ground_offset is off by default)
    est = Estimator3D([short], "box", load_config(None, {"solver3d": {"ground_offset_sigma": 0.005}}))
    pr = est.problem
    assert pr.effects == ("ground_offset", "edge_radius")
    J = _assert_derivatives_match_finite_differences(est)
    # the effects' columns (ground offset, rounded edges) are live, so the checks above
    # cover their derivatives: both move the vertex gaps of every sample
    for name in ("ground_offset", "edge_radius"):
        assert np.abs(J[: pr.n_res_data, pr.theta_index(name)]).max() > 1e-2


def test_derivatives_with_a_pushing_fingertip_match_finite_differences(monkeypatch):
    """The same checks on 8 samples of a fingertip pushing a box (no pose observations):
    the finger terms (force, normal, contact, cone, dissipation) are live and their
    Jacobian columns are checked."""
    monkeypatch.setenv("TACEST_NO_COMPILE", "1")
    from tacest.estimation.estimator3d import Estimator3D
    from tests.test_initial3d import _push_run

    run = _push_run(yaw_deg=3.0)
    a, b = 150, 158  # inside the push: touching at every sample
    short = run.replace(time=run.time[a:b] - run.time[a], finger_position=run.finger_position[a:b],
                        contact=run.contact[a:b], force=run.force[a:b], normal=run.normal[a:b])
    est = Estimator3D([short], "box")
    J = _assert_derivatives_match_finite_differences(est, seed=4)
    lf = slice(est.problem.lf_offset, est.problem.lf_offset + 3 * (short.n_samples - 1))
    assert np.abs(J[:, lf]).max() > 1e-2  # the finger impulses reach the residuals


def test_noiseless_tosses_give_back_the_box(tosses):
    from tacest.estimation.estimator3d import estimate_3d as estimate_runs_3d

    est = estimate_runs_3d(tosses, "box")
    assert est.success, est.solver_status
    extents = np.ptp(est.vertices, axis=0)
    # 1 % (1 mm): the simulated data are the model's solution with near-hard dynamics and
    # soft contact penalties, the estimate the same model with process noise, so the two
    # optima differ by a fraction of the penetration sigma (0.5 mm) at the contacts
    # (0.3 % seen with sharp edges held); with the rounded-edge augmentation free (the
    # default) a sub-millimetre radius trades against the extents: 1.5 % (1.2 % seen)
    np.testing.assert_allclose(extents, EXTENTS, rtol=0.015)
    # friction: 5 %, seen only in the sliding samples of two tosses (1 % seen)
    assert est.params["friction_ground"] == pytest.approx(FRICTION, rel=0.05)
    # inertia over mass (what pose data can tell): principal moments within 10 %, told
    # only by a few impacts (7 % seen)
    true = np.linalg.eigvalsh(polytope_inertia(box_vertices_3d(EXTENTS), MASS) / MASS)
    np.testing.assert_allclose(np.linalg.eigvalsh(est.params["inertia"] / est.params["mass"]), true, rtol=0.10)
    # pose-only data: the mass is the prior's, flagged, with no information
    assert est.identifiable["mass"] is False
    k = est.info_names.index("mass")
    assert np.all(est.information[k] == 0) and np.isinf(est.std["mass"])
    # the trajectory follows the (noiseless) observations to well below a millimetre
    pos = np.concatenate([r.pose[:, :3] - t.pose_obs[:, :3] for r, t in zip(est.runs, tosses)])
    assert np.sqrt(np.mean(np.sum(pos ** 2, 1))) < 5e-4
    # pose-observed runs solve once from their observations: no push-tracked starts
    assert "starts" not in est.extra_attrs


def _augmented_tosses(edge_radius=0.0, ground_height=0.0, effect_params=None):
    """The two noiseless tosses of the box by the project's own 3-D model, with rounded
    edges, a ground offset and further effects (simulate_toss's arguments)."""
    from tacest.estimation.rollout3d import simulate_toss

    inertia = polytope_inertia(box_vertices_3d(EXTENTS), MASS)
    runs = []
    for axis, angle, v, w in (((1.0, 2.0, 0.5), 0.6, (0.5, -0.2, -0.4), (4.0, -6.0, 2.0)),
                              ((0.5, -1.0, 0.2), 1.0, (0.6, 0.3, -0.3), (3.0, 2.0, -5.0))):
        q0 = quat_from_axis_angle(np.array(axis), angle)
        run = simulate_toss("box", EXTENTS, MASS, inertia, FRICTION, np.r_[0.0, 0.0, 0.15, q0], np.r_[v, w], 55,
                            edge_radius=edge_radius, ground_height=ground_height, effect_params=effect_params)
        assert run.extra_attrs["simulation_unconverged_steps"] == 0
        runs.append(run)
    return runs


def test_rounded_edges_are_recovered_and_the_box_keeps_its_size():
    """Known answer for the augmentation ``edge_radius`` (on by default): tosses of a box
    with 6 mm rounded edges give back the radius and the outer extents."""
    from tacest.estimation.estimator3d import estimate_3d as estimate_runs_3d

    est = estimate_runs_3d(_augmented_tosses(0.006, 0.0), "box")
    assert est.success, est.solver_status
    assert "edge_radius" in est.model
    # 1 mm on a 6 mm radius: the radius is told by the tilted contacts of two tosses only
    assert est.params["edge_radius"] == pytest.approx(0.006, abs=1e-3)
    # 1.5 %: as the sharp box's 1 %, plus the radius's uncertainty on the outer size
    np.testing.assert_allclose(np.ptp(est.vertices, axis=0), EXTENTS, rtol=0.015)


def test_sharp_box_gets_a_small_edge_radius(tosses):
    from tacest.estimation.estimator3d import estimate_3d as estimate_runs_3d

    est = estimate_runs_3d(tosses, "box")
    # 1 mm: the prior is a half-normal at 0; noiseless sharp tosses leave it near 0
    assert 0.0 <= est.params["edge_radius"] < 1e-3


def test_a_ground_offset_is_found_when_estimated():
    """Known answer for the augmentation ``ground_offset``: the ground simulated 4 mm
    above where the run files say is found with the box's size right (sharp edges held)."""
    from tacest.estimation.config import load_config
    from tacest.estimation.estimator3d import estimate_3d as estimate_runs_3d

    cfg = load_config(overrides={"solver3d": {"ground_offset_sigma": 0.01, "edge_radius_sigma": 0.0}})
    est = estimate_runs_3d(_augmented_tosses(0.0, 0.004), "box", cfg)
    assert est.success, est.solver_status
    assert est.model == ["ground_offset"] and "edge_radius" not in est.params
    # 1 mm on 4 mm, 2 % on the extents: two tosses only, and the offset trades against the
    # box's size along the ground normal (0.85 mm and 1.5 % seen)
    assert est.params["ground_offset"] == pytest.approx(0.004, abs=1e-3)
    np.testing.assert_allclose(np.ptp(est.vertices, axis=0), EXTENTS, rtol=0.02)
    assert "ground_offset" in est.info_names and np.isfinite(est.std["ground_offset"])


# ---------------------------------------------------------------------------------
# the command line: estimate, eval, failures


def _tacest(*args, cwd=None):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, cwd=cwd)


def test_estimate_and_eval_a_3d_run_through_the_cli(tosses, tmp_path):
    runs = []
    for i, run in enumerate(tosses):
        path = tmp_path / f"toss{i}.h5"
        write_run(run, path)
        runs.append(path)
    est_path = tmp_path / "est.h5"
    r = _tacest("estimate", *runs, "--shape", "box", "--quiet", "-o", est_path)
    assert r.returncode == 0, r.stderr
    r = _tacest("eval", est_path, "--truth", runs[1], "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["dim"] == 3 and rep["run_index"] == 1 and rep["matched_by"] == "sha256"
    # shape 1 % off at most (see the known-answer test): about a millimetre of Chamfer
    assert rep["chamfer_body"] < 2e-3 and rep["chamfer"] < 3e-3
    assert rep["pose_position_rmse"] < 1e-3 and rep["pose_angle_rmse"] < 0.01
    assert rep["friction_ground_rel"] < 0.1
    assert rep["params"]["mass"]["identifiable"] is False
    assert rep["mass_rel"] == pytest.approx(abs(0.5 - MASS) / MASS)  # the prior's 0.5 kg, honestly


def _assert_exit_2(result, *fragments):
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("tacest: error:"), result.stderr
    for frag in fragments:
        assert frag in lines[0], lines[0]


def test_bad_3d_input_exits_2_without_output(tosses, tmp_path):
    short = tosses[0].replace(time=tosses[0].time[:3], pose_obs=tosses[0].pose_obs[:3], truth=None)
    write_run(short, tmp_path / "short.h5")
    out = tmp_path / "est.h5"
    _assert_exit_2(_tacest("estimate", tmp_path / "short.h5", "--quiet", "-o", out), "at least 4 samples")
    write_run(tosses[0], tmp_path / "ok.h5")
    _assert_exit_2(_tacest("estimate", tmp_path / "ok.h5", "--shape", "polygon:5", "--quiet", "-o", out),
                   "polygon:5")
    _assert_exit_2(_tacest("estimate", tmp_path / "ok.h5", "--method", "shooting", "--quiet", "-o", out),
                   "implicit")
    assert not out.exists()


def test_a_failed_3d_solve_exits_2_without_output(tosses, tmp_path):
    write_run(tosses[0], tmp_path / "ok.h5")
    cfg = tmp_path / "few.toml"
    cfg.write_text("[solver]\nmax_iter = 2\n")  # the 3-D stage cannot converge in 2 iterations
    out = tmp_path / "est.h5"
    _assert_exit_2(_tacest("estimate", tmp_path / "ok.h5", "--config", cfg, "--quiet", "-o", out), "IPOPT failed",
                   "Maximum_Iterations_Exceeded")
    assert not out.exists()


def test_a_3d_run_without_observations_or_fingers_is_refused():
    from tacest.estimation.estimator3d import check_runs_3d

    run = Run(dim=3, dt=0.01, time=np.arange(5) * 0.01, gravity=np.array([0.0, 0.0, -9.81]))
    with pytest.raises(TacestError, match="neither pose observations nor fingertip"):
        check_runs_3d([run])


# ---------------------------------------------------------------------------------
# diagnose on 3-D runs


def test_diagnose_3d_finds_rounded_edges_on_held_out_tosses(tmp_path):
    """Tosses of a box with 6 mm rounded edges: the plain (sharp) model leaves a held-out
    gap that the edge_radius augmentation closes, and the verdict says so."""
    runs = _augmented_tosses(0.006, 0.0)
    # training: tosses 0, 1; held out: the same two.  tacest refuses the same run file
    # twice (equal SHA-256), so the held-out copies say what they are: deliberately the
    # training samples, which tests the gap and its reduction, not generalisation
    held = [run.replace(extra_attrs={**run.extra_attrs, "copy_of": f"toss{i}"}) for i, run in enumerate(runs)]
    paths = []
    for i, run in enumerate(runs + held[::-1]):
        p = tmp_path / f"toss{i}.h5"
        write_run(run, p)
        paths.append(p)
    out = _tacest("diagnose", *paths, "--shape", "box", "-o", tmp_path / "diag", "--json", "--quiet")
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    assert {"verdict", "effects", "where"} <= set(d)
    eff = {e["name"]: e for e in d["effects"]}
    # every 3-D augmentation the tosses can show: no force stream, so no force effects
    assert set(eff) == {"edge_radius", "ground_offset", "restitution", "angular_damping", "linear_drag",
                        "soft_contact", "face_friction", "com_offset", "time_scale"}
    assert {"force_bias", "force_scale", "latency"} <= set(d["not_compared"])
    # where[].run is the run's index in 3-D as in 2-D (SPEC's where: run, start, stop, term, share)
    assert all(isinstance(w["run"], int) and w["file"].endswith(".h5") for w in d["where"])
    # the sharp model misses the rounded contacts: a gap above the floor that the rounded
    # model closes by at least the blaming rule's 20 %
    assert eff["edge_radius"]["gap_before"] > 0
    assert eff["edge_radius"]["reduction"] >= 0.2
    assert d["verdict"] == "edge_radius"
    assert (tmp_path / "diag" / "report.md").is_file() and (tmp_path / "diag" / "residuals_3d.png").is_file()


#: every SPEC effect the 3-D NLP models beside edge_radius and ground_offset
EFFECTS_3D = ("angular_damping", "linear_drag", "soft_contact", "force_bias", "force_scale", "face_friction",
              "com_offset")


def test_derivatives_with_every_3d_effect_match_finite_differences(monkeypatch):
    """The checks of the pushing fingertip with every 3-D effect in the model: their
    Jacobian columns are live (each moves some residual of the push) and match central
    differences, as do the gradient and the exact Hessian."""
    monkeypatch.setenv("TACEST_NO_COMPILE", "1")
    from tacest.estimation.estimator3d import Estimator3D
    from tests.test_initial3d import _push_run

    run = _push_run(yaw_deg=3.0)
    a, b = 150, 158
    short = run.replace(time=run.time[a:b] - run.time[a], finger_position=run.finger_position[a:b],
                        contact=run.contact[a:b], force=run.force[a:b], normal=run.normal[a:b])
    est = Estimator3D([short], "box", effects=EFFECTS_3D)
    pr = est.problem
    assert set(EFFECTS_3D) <= set(pr.effects)
    J = _assert_derivatives_match_finite_differences(est, seed=5)
    for e, par in pr.effect_params:
        if e.name in EFFECTS_3D:
            col = np.abs(J[: pr.n_res_data, pr.theta_index(f"{e.name}.{par.name}")]).max()
            if e.name == "face_friction":  # only the face the box rests on (d2: -z) slides
                assert (col > 1e-3) == (par.name == "d2"), (par.name, col)
            else:
                assert col > 1e-3, f"{e.name}.{par.name} moves no residual"


def test_face_friction_is_refused_for_a_polytope_in_3d():
    from tacest.errors import TacestError
    from tacest.geometry.shapes3d import make_shape_3d
    from tacest.model.stage3d import StageModel3D

    with pytest.raises(TacestError, match="face_friction"):
        StageModel3D(make_shape_3d("polytope:8"), 1, ("face_friction",))


@pytest.mark.parametrize("spec,keys,tol", [
    # 3 % of the offsets: the force stream sees the bias at every sample (0.1 % seen)
    ("force_bias:fx=0.5,fy=-0.3,fz=0.4", {"force_bias.fx": 0.5, "force_bias.fy": -0.3, "force_bias.fz": 0.4}, 0.015),
    # 2.5 mm on offsets of 8-16 mm: told by how the box tips and rests (0.4, 0.4, 1.3 mm seen)
    ("com_offset:dx=0.016,dy=-0.008,dz=0.011", {"com_offset.dx": 0.016, "com_offset.dy": -0.008,
                                                 "com_offset.dz": 0.011}, 0.0025),
])
def test_a_3d_effect_is_recovered_from_a_recording_that_shows_it(spec, keys, tol):
    """Known answer for a 3-D augmentation on a recording of the MuJoCo world (another
    simulator than the model): 3 dynamic pokes by one force-sensing finger, poses seen at
    0.5 mm.  The effect's parameters come back, and the fit with the effect explains the
    data far better than the plain one."""
    from tacest.dims import record_sim
    from tacest.estimation.estimator3d import estimate_3d
    from tacest.sim.record import SimOptions

    run = record_sim(SimOptions(dim=3, seed=1, pokes=3, fingers=1, effects=[spec], observe_pose=0.0005,
                                poke_style="dynamic"))
    name = spec.split(":")[0]
    plain = estimate_3d([run], "box")
    est = estimate_3d([run], "box", effects=[name])
    assert est.success, est.solver_status
    assert name in est.model
    for k, v in keys.items():
        assert est.params[k] == pytest.approx(v, abs=tol), k
        assert np.isfinite(est.std[k])
    # the plain fit pays for the missing effect (objective 34214 -> 1447 for the bias,
    # 29346 -> 1324 for the COM): at least a factor 5
    assert est.objective < plain.objective / 5


@pytest.mark.parametrize("name,key,value", [("linear_drag", "linear_drag.b", 0.5),
                                            ("angular_damping", "angular_damping.c", 0.002)])
def test_drag_and_damping_are_recovered_from_tosses_that_show_them(name, key, value):
    """Known answer for the 3-D augmentations a flight shows: two noiseless tosses of the
    box simulated by the project's own 3-D model with the effect (b = 0.5 N·s/m slows a
    0.4 kg box by 1.25 /s; c = 0.002 N·m·s its spin by about 2.5 /s).  The fit with the
    effect gives it back within 2.5 of its reported stds (0.8 and 0.55 seen: the stds
    are those of the configured 1 mm / 0.01 rad pose noise, the data are noiseless) and
    explains the tosses better than the plain fit (objective 19 -> 9.5 and 16 -> 8.5 seen)."""
    from tacest.estimation.estimator3d import estimate_3d

    runs = _augmented_tosses(effect_params={key: value})
    for run in runs:
        assert run.truth.effects == [{"name": name, key.split(".")[1]: value}]
    plain = estimate_3d(runs, "box")
    est = estimate_3d(runs, "box", effects=[name])
    assert est.success, est.solver_status
    assert 0 < est.std[key] < value  # identified: the std below the value itself
    assert abs(est.params[key] - value) < 2.5 * est.std[key]
    assert est.objective < 0.75 * plain.objective
    np.testing.assert_allclose(np.ptp(est.vertices, axis=0), EXTENTS, rtol=0.015)


def test_a_nested_fit_from_the_plain_optimum_ends_at_or_below_it():
    """estimator3d.solve_warm (the 3-D diagnosis' second start for a candidate whose own
    fit ends above the plain model): started at the plain fit's optimum with the drag at
    0, the drag model of tosses that show b = 0.5 N·s/m ends below the plain objective
    (it nests the plain model) and finds the drag within 2.5 reported stds, as a fit
    from its own start does (test above).  A solution of another problem's size is
    refused."""
    from tacest.estimation.estimator3d import Estimator3D, solve_warm

    runs = _augmented_tosses(effect_params={"linear_drag.b": 0.5})
    plain = Estimator3D(runs, "box")
    out_p = plain.solve()
    drag = Estimator3D(runs, "box", effects=["linear_drag"])
    out = solve_warm(drag, out_p.z, plain.s0)
    assert out.objective <= out_p.objective
    est = drag.result(out, 0.0)
    assert abs(est.params["linear_drag.b"] - 0.5) < 2.5 * est.std["linear_drag.b"]
    with pytest.raises(TacestError, match="does not fit"):
        solve_warm(drag, out_p.z[:10], plain.s0)


@pytest.mark.slow
def test_diagnose_3d_from_touch_alone_finds_a_force_bias():
    """The 3-D diagnosis without pose observations (touch alone): MuJoCo pokes by one
    force-sensing finger whose sensor reads (0.33, -0.34, 0.35) N too much, cut at the
    pokes.  The plain model's held-out loss is above the shared floor, the force_bias
    candidate (fitted from the plain optimum) closes most of it and gives the bias back
    to 0.02 N (the force noise is 0.02 N per sample and the bias is seen on every one of
    hundreds of samples: a few mN is its standard error); the verdict names it."""
    from tacest.diagnosis.diagnose3d import Options3D, diagnose_3d
    from tacest.io.slicing import split_at_actions
    from tacest.dims import record_sim
    from tacest.sim.record import SimOptions

    pytest.importorskip("mujoco")
    run = record_sim(SimOptions(dim=3, seed=0, pokes=4, fingers=1, effects=["force_bias"], poke_style="gentle"))
    truth = run.truth.effects  # SPEC: one object {"name": ..., parameters}
    parts = [p.replace(filename=f"part{i}", truth=None) for i, p in enumerate(split_at_actions(run))]
    assert all(p.pose_obs is None for p in parts)
    d = diagnose_3d(parts, "box", options=Options3D(effects=("force_bias", "linear_drag")))
    eff = {e["name"]: e for e in d.effects}
    assert eff["force_bias"]["gap_before"] > 0
    assert eff["force_bias"]["reduction"] >= 0.5
    assert d.verdict == "force_bias"
    for a in "xyz":
        assert eff["force_bias"]["params"][f"force_bias.f{a}"] == pytest.approx(truth[f"f{a}"], abs=0.02)
    assert eff["force_bias"]["counts"] and eff["force_bias"]["improvement"] > eff["force_bias"]["penalty"]
    json.dumps(d.to_json(), allow_nan=False)  # strict JSON: a term without data has no level (None), not NaN


def test_diagnose_3d_finds_a_clock_error_on_tosses(tmp_path):
    """The transform candidate time_scale in 3-D: tosses whose clock runs 6 % fast (every
    time stamp and dt times 1.06: gravity appears as g / 1.06²) are blamed on it, with the
    scale within a grid step (1.5 %) of the truth; edge_radius is compared beside it."""
    from tacest.diagnosis.diagnose3d import Options3D, diagnose_3d

    runs = _augmented_tosses(0.0, 0.0)
    fast = [r.replace(dt=r.dt * 1.06, time=r.time * 1.06, filename=f"toss{i}") for i, r in enumerate(runs)]
    held = [r.replace(extra_attrs={**r.extra_attrs, "copy_of": r.filename}, filename=r.filename + "b") for r in fast]
    d = diagnose_3d(fast + held[::-1], "box", options=Options3D(effects=("time_scale", "edge_radius")))
    eff = {e["name"]: e for e in d.effects}
    assert set(eff) == {"time_scale", "edge_radius"}
    assert d.verdict == "time_scale", d.reason
    assert d.fits["time_scale"].params["time_scale.scale"] == pytest.approx(1.06, abs=0.016)


def test_a_force_gain_is_recovered_in_3d_when_the_mass_is_weighed():
    """force_scale in 3-D: a gain is the mass's twin unless the mass is known; with the
    mass weighed (prior at +2 %, log sigma 0.02) a recorded gain of 1.3 (MuJoCo, 3 dynamic
    pokes) comes back within 2.5 of its std (1.20 ± 0.056 seen: the +2 % on the mass moves
    it by -2 %, the rest is the fit's)."""
    from tacest.dims import record_sim
    from tacest.estimation.config import load_config
    from tacest.estimation.estimator3d import estimate_3d
    from tacest.sim.record import SimOptions

    run = record_sim(SimOptions(dim=3, seed=1, pokes=3, fingers=1, effects=["force_scale:gain=1.3"],
                                observe_pose=0.0005, poke_style="dynamic"))
    cfg = load_config(overrides={"prior": {"mass": run.truth.mass * 1.02, "mass_log_sigma": 0.02}})
    est = estimate_3d([run], "box", cfg, effects=["force_scale"])
    assert est.success, est.solver_status
    assert abs(est.params["force_scale.gain"] - 1.3) < 2.5 * est.std["force_scale.gain"]


def test_a_soft_ground_is_found_on_tosses_with_its_known_bias():
    """soft_contact in 3-D (quasi-static sink) on two noiseless tosses of the project's own
    model onto a ground of compliance 0.5 mm/N: the fit with the effect explains the
    landings (objective 267 -> 25 seen) and finds the compliance 21 % low, the box 1-2 %
    larger (a larger box sinks less for the same centre height: the two trade).  A known
    limit, asserted as such: within 30 %, and the reported std (7 %) does not cover the
    trade-off (docs/estimation3d.md, "Effects")."""
    from tacest.estimation.estimator3d import estimate_3d

    runs = _augmented_tosses(effect_params={"soft_contact.compliance": 0.0005})
    for run in runs:
        assert run.truth.effects == [{"name": "soft_contact", "damping": 0.0, "stiffness": 2000.0}]
    plain = estimate_3d(runs, "box")
    est = estimate_3d(runs, "box", effects=["soft_contact"])
    assert est.success, est.solver_status
    assert est.params["soft_contact.compliance"] == pytest.approx(0.0005, rel=0.30)
    assert est.objective < 0.25 * plain.objective


def test_a_force_stream_that_never_touched_leaves_the_mass_at_its_prior():
    """A pose-observed toss recorded with a force stream that the parked finger never
    used (``record --dim 3 --toss --pokes 0 --observe-pose``): such a stream tells nothing
    of the mass (tacest.estimation.data.force_in_contact), so the mass is held at its
    prior and reported not identifiable, and the fit solves.  Left free, the mass shrank
    every physics residual with it: 0.004 kg for 0.48, IPOPT's iteration limit on 7 of 8
    seeds.  With one touch the stream counts."""
    from tacest.dims import record_sim
    from tacest.estimation.config import EstimatorConfig
    from tacest.estimation.data import force_in_contact
    from tacest.estimation.estimator3d import estimate_3d
    from tacest.sim.record import SimOptions

    run = record_sim(SimOptions(dim=3, toss=True, pokes=0, seed=3, observe_pose=1e-3))
    assert run.force is not None and not run.contact.any()
    assert not force_in_contact([run])
    est = estimate_3d([run], "box")
    assert est.success and est.params["mass"] == pytest.approx(EstimatorConfig().prior.mass)
    assert est.identifiable["mass"] is False
    touched = Run(**{**run.__dict__})
    touched.contact = run.contact.copy()
    touched.contact[5, 0] = 1
    assert force_in_contact([run, touched]) and not force_in_contact([Run(**{**touched.__dict__, "force": None})])


def _folds(shape, s, L=1.0):
    """(M,) per face of ``shape.faces``: the largest height (units of L) of any point of
    the shape at s above that face's plane (≤ 0 where the fixed triangulation is the
    points' hull)."""
    from tacest.geometry.shapes3d import numeric_vertices_3d

    V = numeric_vertices_3d(shape, s, L) / L
    out = []
    for i, j, k in shape.faces:
        n = np.cross(V[j] - V[i], V[k] - V[i])
        out.append(np.max((V - V[i]) @ (n / np.linalg.norm(n))))
    return np.array(out)


def test_a_round_polytope_start_is_its_own_hull():
    """polytope:K's finger signed distance is the largest height over the planes of a
    FIXED triangulation: right where that triangulation is the points' hull, as for
    equal radii (the Fibonacci directions themselves)."""
    from tacest.geometry.shapes3d import make_shape_3d

    for K in (8, 12, 20):
        shape = make_shape_3d(f"polytope:{K}")
        assert _folds(shape, np.ones(K)).max() <= 1e-12


@pytest.mark.xfail(strict=True, reason="known limitation (docs/estimation3d.md, 'Limits'): polytope:K starts with "
                   "its support points on the surface of a box, where its fixed triangulation folds (a point up to "
                   "0.1-0.2 L above a neighbouring face's plane), so the fingertip's signed distance is not that of "
                   "the points' hull")
def test_a_polytope_started_from_a_box_is_its_own_hull():
    from tacest.geometry.shapes3d import make_shape_3d

    shape = make_shape_3d("polytope:12")
    for extents in ([1.0, 0.8, 0.6], [1.2, 0.5, 0.8]):
        # 1 % of L: below the touches' resolution
        assert _folds(shape, shape.initial(np.array(extents))).max() <= 0.01

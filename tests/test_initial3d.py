"""Starts of the 3-D estimator without pose observations (initial3d.py) and its restarts
(Estimator3D.solve): synthetic pushes, no NLP built, quick."""

from __future__ import annotations

from types import SimpleNamespace

import re

import numpy as np
import pytest

from tacest.errors import SolveFailedError
from tacest.estimation import estimator3d
from tacest.estimation.config import EstimatorConfig
from tacest.errors import TacestError
from tacest.estimation.initial3d import (EXTENT_GRID, Start3D, continued_track, finger_gaps_3d, push_tracker_3d,
                                         start_candidates_3d, touch_inconsistency_3d, yaw_track)
from tacest.geometry.shapes3d import make_shape_3d, numeric_vertices_3d
from tacest.io.estimate import Estimate, RunEstimate
from tacest.estimation.solver import SolveOutcome, StageInfo
from tacest.io.run import Run

DT = 0.01
RADIUS = 0.01  # m, fingertip radius
BOX = np.array([0.12, 0.08, 0.06])  # m, extents of the pushed box


def _push_run(yaw_deg: float = 0.0, edge_normal: bool = False) -> Run:
    """A fingertip approaching the box (at rest at the origin) along +x at mid-height,
    touching its -x face and pushing it 4 cm at 2 cm/s, then leaving.  The measured
    normal is the -x face's outward normal turned by yaw_deg about z (the object's yaw
    while pushed); with edge_normal, the first 5 touching samples report an edge normal
    at 45°, as a touch at a vertical edge does."""
    T = 400
    x_face = -BOX[0] / 2 - RADIUS  # the fingertip centre when touching the unmoved face
    x = np.full(T, x_face - 0.03)
    approach = np.arange(50, 100)
    x[approach] = np.linspace(x_face - 0.03, x_face, len(approach))
    push = np.arange(100, 300)
    x[push] = x_face + 0.02 * DT * (push - 100)  # 2 cm/s for 2 s: 4 cm
    x[300:] = x[299] - 0.01
    contact = np.zeros((T, 1), np.uint8)
    contact[push] = 1
    a = np.radians(180.0 + yaw_deg)
    normal = np.full((T, 1, 3), np.nan)
    normal[push, 0] = [np.cos(a), np.sin(a), 0.0]
    if edge_normal:
        normal[100:105, 0] = [np.cos(np.radians(225)), np.sin(np.radians(225)), 0.0]
    fp = np.stack([x, np.zeros(T), np.full(T, BOX[2] / 2)], 1)[:, None, :]
    force = np.zeros((T, 1, 3))
    force[push, 0, 0] = 2.0
    return Run(dim=3, dt=DT, time=np.arange(T) * DT, gravity=np.array([0.0, 0.0, -9.81]), source="test",
               finger_position=fp, finger_radius=np.array([RADIUS]), contact=contact, force=force, normal=normal)


def test_the_tracked_box_follows_the_push_and_the_finger_is_never_deep_inside():
    run = _push_run()
    poses = push_tracker_3d(run, BOX[None])[0]  # (T, 7)
    # resting on the ground (its centre half a height up), never tipped
    np.testing.assert_allclose(poses[:, 2], BOX[2] / 2, atol=1e-12)
    np.testing.assert_allclose(poses[:, 3], 1.0, atol=1e-12)
    # pushed 4 cm along +x within 1 mm (the tracker clears the fingertip one sample
    # late: at most one sample's 0.2 mm of travel behind), no sideways drift
    assert poses[0, 0] == 0.0
    assert poses[-1, 0] == pytest.approx(0.04, abs=1e-3)
    np.testing.assert_allclose(poses[:, 1], 0.0, atol=1e-12)
    gaps = finger_gaps_3d(run, BOX[None], poses[None])[0, :, 0]
    # the fingertip is never deeper than 1e-9 m (rounding) after the tracker's step:
    # the tracker moves within the sample the finger arrives
    assert gaps.min() > -1e-9
    # the untracked resting box would have the finger 4 cm inside: the tracker is what fixes it
    rest = np.repeat(poses[:1], run.n_samples, 0)
    assert finger_gaps_3d(run, BOX[None], rest[None])[0, :, 0].min() < -0.03


def test_the_yaw_follows_side_normals_and_ignores_an_edge_touch():
    turned = yaw_track(_push_run(yaw_deg=6.0))
    # the normals say 6°: the tracked yaw is 6° once YAW_MIN_SAMPLES touches agree
    assert np.degrees(turned[-1]) == pytest.approx(6.0, abs=1e-9)
    assert turned[0] == 0.0
    # 5 edge normals at 45° (beyond YAW_ACCEPT = 10° of the current yaw) do not turn it
    edge = yaw_track(_push_run(yaw_deg=0.0, edge_normal=True))
    assert np.max(np.abs(np.degrees(edge))) < 1e-9
    # the tracked quaternion is the yaw about z
    q = push_tracker_3d(_push_run(yaw_deg=6.0), BOX[None])[0, -1, 3:]
    np.testing.assert_allclose(q, [np.cos(np.radians(3.0)), 0, 0, np.sin(np.radians(3.0))], atol=1e-12)


def test_candidates_rank_the_touched_width_and_include_the_resting_start():
    run = _push_run()
    L = 0.1
    starts = start_candidates_3d([run], L, np.ones(3), 3)
    assert len(starts) == 3
    assert starts[-1].label == "resting" and starts[-1].poses is None
    assert starts[0].label == "push-tracked"
    # the box rests at the origin and the finger first touches its -x face: a narrower
    # box leaves the finger outside while it touches, a wider one puts it inside before
    # (the tracker only pushes touching fingers); the best width is the true one within
    # one step of the grid (a factor 2.0 / 0.4 over 10 steps, 17.5 %)
    best = starts[0]
    step = (EXTENT_GRID[1] / EXTENT_GRID[0])
    assert abs(np.log(best.extents[0] * L / BOX[0])) < np.log(step)
    # and keeps the touching finger on its surface within half a grid step of the width
    # (the face offset of a width off by a fraction of a step), 0.1 m x 17.5 % / 2 ≈ 9 mm
    gaps = finger_gaps_3d(run, best.extents[None] * L, best.poses[0][None])[0, :, 0]
    assert np.all(np.abs(gaps[run.contact[:, 0] == 1]) < 0.5 * (step - 1) * L)
    # a clearly wrong box costs more
    wrong = np.array([[0.05, 0.08, 0.06]])
    assert touch_inconsistency_3d(run, wrong, push_tracker_3d(run, wrong))[0] > 10 * best.inconsistency + 1e-6


class _FakeProblem:
    n_shape = 3


def _fake_estimator(monkeypatch, outcomes, restart_physics=0.1, restarts=2, compare=False, pushed=3):
    """An Estimator3D without an NLP: its per-start solves return (objective, physics) of
    ``outcomes`` in turn (None: the solve fails; (objective, physics, status): a fit
    ending with that IPOPT status, e.g. its iteration budget used up); ``compare``:
    solver3d.compare_starts (off: the restart logic alone); ``pushed``:
    solver3d.compared_push_tracked.  ``est.found`` counts the starts taken from the
    start search."""
    est = estimator3d.Estimator3D.__new__(estimator3d.Estimator3D)
    # the sampled start is off here (its place among the starts: test_a_tipping_sampled_start_goes_first)
    cfg = EstimatorConfig().updated({"solver3d": {"restart_physics": restart_physics, "restarts": restarts,
                                                  "sampler_particles": 0, "compare_starts": compare,
                                                  "compared_push_tracked": pushed},
                                     # the fake solves note their calls here: one process
                                     "solver": {"start_workers": 1}})
    est.config, est.problem = cfg, _FakeProblem()
    est.runs, est.has_pose, est.fixed_theta, est.F = [_push_run()], False, None, 1
    est.shape = estimator3d.make_shape_3d("box")
    est.scales = type("S", (), {"L": 0.1})()
    est.start_tracks, est.attempts, est.accept_budget = None, [], False
    starts = [Start3D(np.full(3, 1.0 + 0.3 * k), [np.zeros((400, 7))], f"start {k}", float(k)) for k in range(3)]
    est.found = 0

    def candidates(runs, L, rest, n, starts=starts):
        for c in starts[:n]:
            est.found += 1
            yield c

    monkeypatch.setattr(estimator3d, "iter_start_candidates_3d", candidates)
    calls = []
    offered = est.offered_starts = []

    def solve_from(s0, accept_budget=None, abandon_above=float("inf")):
        k = len(calls)
        calls.append(np.asarray(s0, float))
        # the start's trajectory is used (a sampled start, when one is offered, is another)
        assert any(est.start_tracks is c.poses for c in (starts + offered if offered else starts[k:k + 1]))
        # every start's final stage may end on its budget: solve_from_starts judges
        assert accept_budget is True
        if outcomes[k] is None:
            raise SolveFailedError("IPOPT failed in stage 'homotopy 1/1': Maximum_Iterations_Exceeded")
        obj, phys, status = (*outcomes[k], "Solve_Succeeded")[:3]
        est.p_final, est.bounds_final = ("p", k), ("b", k)
        stage = StageInfo(name="homotopy 2/2", status=status, iterations=800, wall_time=0.0, objective=obj)
        return SolveOutcome(z=np.array([obj, phys]), lam_g=np.zeros(0), lam_x=None, status=status,
                            success=status == "Solve_Succeeded", iterations=800, wall_time=0.0, objective=obj,
                            stages=[stage])

    monkeypatch.setattr(est, "solve_from_shape", solve_from)
    monkeypatch.setattr(est, "physics_per_sample", lambda z: float(z[1]))
    # the fits' own data are not tested here (local None: only their physics decides;
    # tests/test_restarts.py has the two together), and what they found is a stand-in
    monkeypatch.setattr(est, "fit_quality", lambda z: SimpleNamespace(local=None))
    monkeypatch.setattr(est, "physical", lambda z: (np.zeros((8, 3)), 1.0, np.eye(3), 0.5, 0.5))
    return est, calls


def test_restart_keeps_the_successful_fit_of_lowest_objective(monkeypatch):
    # start 0 violates its physics, start 1 fails, start 2 violates too but has the lower objective
    est, calls = _fake_estimator(monkeypatch, [(50.0, 0.5), None, (30.0, 0.3)])
    out = est.solve()
    assert len(calls) == 3
    assert out.objective == 30.0 and est.p_final == ("p", 2) and est.bounds_final == ("b", 2)
    np.testing.assert_allclose(est.s0, calls[2])
    assert [a["status"] for a in est.attempts] == ["Solve_Succeeded", "failed", "Solve_Succeeded"]
    assert est.start_tracks is None
    # the lower objective wins even when it came first
    est, calls = _fake_estimator(monkeypatch, [(20.0, 0.5), (40.0, 0.3), (60.0, 0.2)])
    assert est.solve().objective == 20.0 and len(calls) == 3


def test_no_restart_after_a_physically_consistent_fit(monkeypatch):
    est, calls = _fake_estimator(monkeypatch, [(50.0, 0.05), (10.0, 0.01), (5.0, 0.0)])
    assert est.solve().objective == 50.0 and len(calls) == 1


def test_compared_starts_are_all_solved(monkeypatch):
    """solver3d.compare_starts (the default): every start is solved, whatever the first
    fits' physics, and the lowest objective is kept."""
    est, calls = _fake_estimator(monkeypatch, [(50.0, 0.05), None, (5.0, 0.0)], compare=True)
    assert est.solve().objective == 5.0 and len(calls) == 3
    assert [a["status"] for a in est.attempts] == ["Solve_Succeeded", "failed", "Solve_Succeeded"]
    assert EstimatorConfig().solver3d.compare_starts
    # the resting start (no trajectory) goes last and is only a restart: not solved
    # after a good compared fit, solved when none is
    for outcomes, n_calls, kept in (([(50.0, 0.05), (40.0, 0.05), (5.0, 0.0)], 2, 40.0),
                                    ([(50.0, 0.5), (40.0, 0.5), (5.0, 0.0)], 3, 5.0)):
        est, calls = _fake_estimator(monkeypatch, outcomes, compare=True)
        resting = list(estimator3d.iter_start_candidates_3d(None, None, None, 3))
        resting[0] = Start3D(np.ones(3), None, "resting", 0.0)
        est.offered_starts.extend(resting)  # any order of the starts' trajectories
        monkeypatch.setattr(estimator3d, "iter_start_candidates_3d", lambda runs, L, rest, n: iter(resting[:n]))
        assert est.solve().objective == kept and len(calls) == n_calls
        assert [a["start"] for a in est.attempts][-1] == ("resting" if n_calls == 3 else "start 2")


def test_a_fit_that_used_up_its_budget_competes_by_objective(monkeypatch):
    """A start that creeps towards the right basin until its iteration budget ends below
    a converged restart's objective is kept, with its status (success False); it does
    not end the search; without any converged fit it is a failure (exit 2 on the CLI),
    unless the caller accepts budget fits (the diagnosis: they count as converged)."""
    budget = "Maximum_Iterations_Exceeded"
    est, calls = _fake_estimator(monkeypatch, [(51.8, 0.04, budget), (75.8, 0.04), (10.0, 0.0)])
    out = est.solve()
    assert len(calls) == 2  # the converged restart is good: the search ends there
    assert out.objective == 51.8 and out.status == budget and not out.success and est.p_final == ("p", 0)
    assert [a["status"] for a in est.attempts] == [budget, "Solve_Succeeded"]
    # a budget fit of lower objective that violates its physics does not let a good
    # converged fit end the search
    est, calls = _fake_estimator(monkeypatch, [(51.8, 0.5, budget), (75.8, 0.04), (60.0, 0.04)])
    assert est.solve().objective == 51.8 and len(calls) == 3
    # a converged fit of lower objective wins over it
    est, calls = _fake_estimator(monkeypatch, [(51.8, 0.04, budget), (40.0, 0.04)])
    assert est.solve().objective == 40.0
    # budget fits alone, and failures: no estimate
    est, calls = _fake_estimator(monkeypatch, [(51.8, 0.04, budget), None, (60.0, 0.5, budget)])
    with pytest.raises(SolveFailedError, match="no converged fit from any of 3 starts.*homotopy 2/2.*" + budget):
        est.solve()
    assert len(calls) == 3
    # ... unless budget fits are accepted (the diagnosis): they count as converged ones,
    # and a good one ends the search
    est, calls = _fake_estimator(monkeypatch, [(51.8, 0.5, budget), None, (60.0, 0.04, budget)])
    est.accept_budget = True
    assert est.solve().objective == 51.8 and len(calls) == 3
    est, calls = _fake_estimator(monkeypatch, [(51.8, 0.04, budget), None, (60.0, 0.5, budget)])
    est.accept_budget = True
    assert est.solve().objective == 51.8 and len(calls) == 1


def test_every_start_failing_raises_one_solve_failure(monkeypatch):
    est, calls = _fake_estimator(monkeypatch, [None, None, None])
    with pytest.raises(SolveFailedError, match="no converged fit from any of 3 starts.*Maximum_Iterations_Exceeded"):
        est.solve()
    assert len(calls) == 3 and len(est.attempts) == 3


@pytest.mark.parametrize("tilt_deg, first", [(60.0, True), (5.0, False)])
def test_a_tipping_sampled_start_goes_first(monkeypatch, tilt_deg, first):
    """The sampler's lineage is solved first when it tips the box further than
    solver3d.sampler_tip_deg (the push tracker never tips it), else it is the first
    restart; the push-tracked starts keep their order."""
    est, calls = _fake_estimator(monkeypatch, [(50.0, 0.5), (40.0, 0.5), (30.0, 0.5), (20.0, 0.5)])
    est.config = est.config.updated({"solver3d": {"sampler_particles": 256}})
    sampled = Start3D(np.full(3, 0.7), [np.zeros((400, 7))], "sampler", 0.0, extra={"max_tilt_deg": tilt_deg})
    monkeypatch.setattr(est, "sampled_starts", lambda tracked: [sampled])
    est.offered_starts.append(sampled)
    est.solve()
    labels = [a["start"] for a in est.attempts]
    assert labels == (["sampler", "start 0", "start 1", "start 2"] if first else
                      ["start 0", "sampler", "start 1", "start 2"])
    assert est.attempts[labels.index("sampler")]["max_tilt_deg"] == tilt_deg


def test_new_solver3d_keys_are_checked():
    from tacest.errors import TacestError
    from tacest.estimation.config import load_config

    for bad in ({"hessian_no_pose": "newton"}, {"homotopy_no_pose": [[0.3, 1.0]]}, {"restarts": -1},
                {"restart_physics": 0.0}, {"sampler_particles": 1}, {"sampler_runs": 0}, {"sampler_seed": -1}, {"sampler_tip_deg": -1.0},
                {"max_iter_no_pose": 0}):
        with pytest.raises(TacestError, match="solver3d"):
            load_config(overrides={"solver3d": bad})


def test_a_poke_run_whose_every_start_fails_exits_2_without_output(tmp_path):
    """Through the CLI: IPOPT limited to 2 iterations cannot fit any start; one clear
    line, exit status 2, no estimate file."""
    import subprocess
    import sys
    from pathlib import Path

    from tacest.io.run import write_run

    write_run(_push_run(), tmp_path / "push.h5")
    cfg = tmp_path / "few.toml"
    cfg.write_text("[solver]\nmax_iter = 2\nstage_max_iter = 2\n[solver3d]\nmax_iter_no_pose = 2\n")
    out = tmp_path / "est.h5"
    tacest = str(Path(sys.executable).with_name("tacest"))
    r = subprocess.run([tacest, "estimate", str(tmp_path / "push.h5"), "--shape", "box", "--config", str(cfg),
                        "--quiet", "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("tacest: error:"), r.stderr
    # the push-tracked and resting starts and the sampler's
    assert re.search(r"no converged fit from any of [34] starts", lines[0]) and "Maximum_Iterations_Exceeded" in lines[0]
    assert not out.exists()


def test_finger_gaps_with_one_orientation_per_sample_match_the_general_path():
    """finger_gaps_3d's fast path (every box turned alike per sample, the push tracker's)
    gives the general path's gaps: the same boxes with one quaternion negated (the same
    rotation, another array) take the general path; to 1e-12 m (rounding)."""
    run = _push_run()
    boxes = np.array([[0.08, 0.1, 0.12], [0.1, 0.1, 0.1], [0.14, 0.06, 0.09]])
    poses = push_tracker_3d(run, boxes)
    fast = finger_gaps_3d(run, boxes, poses)
    other = poses.copy()
    other[1, :, 3:] *= -1.0
    np.testing.assert_allclose(fast, finger_gaps_3d(run, boxes, other), rtol=0, atol=1e-12)
    assert np.isfinite(fast).all() and fast.min() < 0.0 < fast.max()


def test_a_continued_track_keeps_the_earlier_poses_and_follows_the_newer_push():
    run = _push_run()
    full = push_tracker_3d(run, BOX[None])[0]
    # continued from the tracker's own pose mid-push, it is the tracker's track (to
    # rounding: the same steps from the same pose)
    np.testing.assert_allclose(continued_track(run, BOX, full[:150]), full, atol=1e-12)
    # an earlier trajectory 1 cm aside (+y) and 5 mm further along +x: kept exactly over
    # its samples, then held and pushed on from its last pose; the fingertip is never
    # inside the box after the tracker's step (as test_the_tracked_box_follows_...)
    before = full[:150].copy()
    before[:, :2] += [0.005, 0.01]
    track = continued_track(run, BOX, before)
    np.testing.assert_array_equal(track[:150], before)
    np.testing.assert_allclose(track[150:, 1], 0.01, atol=1e-12)
    assert finger_gaps_3d(run, BOX[None], track[None])[0, 150:, 0].min() > -1e-9
    # the push goes on 2 cm/s until sample 300: it ends where the fingertip left it
    assert track[-1, 0] == pytest.approx(full[-1, 0], abs=1e-3)
    with pytest.raises(ValueError, match="poses_before"):
        continued_track(run, BOX, np.zeros((run.n_samples + 1, 7)))


@pytest.mark.parametrize("spec", ["box", "polytope:12"])
def test_shape_parameters_come_back_from_their_vertices(spec):
    shape = make_shape_3d(spec)
    s = shape.initial(np.array([1.2, 0.8, 0.6])) * np.linspace(0.9, 1.1, shape.n_params)
    V = numeric_vertices_3d(shape, s, 0.1)
    np.testing.assert_allclose(shape.params_from_vertices(V, 0.1), s, rtol=1e-12)


def _earlier_estimate(run, T0, shape="box", dim=3, n_runs=1):
    poses = push_tracker_3d(run, BOX[None])[0][:T0]
    V = numeric_vertices_3d(make_shape_3d("box"), BOX / 0.1, 0.1)
    return Estimate(dim=dim, shape=shape, vertices=V, params={},
                    runs=[RunEstimate(pose=poses, velocity=np.zeros((T0, 6)))] * n_runs)


def test_an_earlier_estimate_is_a_start_with_its_shape_and_continued_trajectory():
    run = _push_run()
    start = estimator3d.previous_start([run], make_shape_3d("box"), _earlier_estimate(run, 150), 0.1)
    assert start.label == "previous estimate"
    np.testing.assert_allclose(start.shape_params, BOX / 0.1, rtol=1e-12)
    np.testing.assert_allclose(start.poses[0], push_tracker_3d(run, BOX[None])[0], atol=1e-12)
    for bad, what in ((_earlier_estimate(run, 150, shape="polytope:12"), "not a 3-D box"),
                      (_earlier_estimate(run, 150, n_runs=2), "has 2 runs"),
                      (_earlier_estimate(run, 150, dim=2), "2-D")):
        with pytest.raises(TacestError, match=what):
            estimator3d.previous_start([run], make_shape_3d("box"), bad, 0.1)
    longer = _push_run()
    longer = _earlier_estimate(longer, 400)
    longer.runs[0].pose = np.concatenate([longer.runs[0].pose, longer.runs[0].pose[-1:]])
    with pytest.raises(TacestError, match="does not fit a run of 400 samples"):
        estimator3d.previous_start([run], make_shape_3d("box"), longer, 0.1)


def test_the_previous_estimate_is_solved_first_and_compared(monkeypatch):
    """An earlier estimate's start (a closed loop's) is solved first, from its own shape
    parameters, and competes by objective with every compared start."""
    est, calls = _fake_estimator(monkeypatch, [(30.0, 0.0), (50.0, 0.05), (40.0, 0.05), (5.0, 0.0)], compare=True)
    prev = Start3D(np.ones(3), [np.zeros((400, 7))], "previous estimate", 0.0, shape_params=np.array([1.1, 0.7, 0.5]))
    est.previous = prev
    est.offered_starts.append(prev)
    out = est.solve()
    np.testing.assert_allclose(calls[0], [1.1, 0.7, 0.5])
    assert [a["start"] for a in est.attempts][0] == "previous estimate"
    # the previous start and the three compared ones are all solved; the lowest kept
    assert len(calls) == 4 and out.objective == 5.0



def test_the_further_push_tracked_starts_are_restarts_searched_for_when_wanted(monkeypatch):
    """solver3d.compared_push_tracked (default 1): the best push-tracked start is
    compared, the further ones are restarts, and the start search is not asked for them
    while a compared fit is good."""
    assert EstimatorConfig().solver3d.compared_push_tracked == 1
    est, calls = _fake_estimator(monkeypatch, [(50.0, 0.05), (40.0, 0.05), (5.0, 0.0)], compare=True, pushed=1)
    assert est.solve().objective == 50.0 and len(calls) == 1 and est.found == 1
    # a compared fit that violates its physics: the further starts are found and solved
    est, calls = _fake_estimator(monkeypatch, [(50.0, 0.5), (40.0, 0.05), (5.0, 0.0)], compare=True, pushed=1)
    assert est.solve().objective == 40.0 and len(calls) == 2 and est.found == 3
    assert [a["start"] for a in est.attempts] == ["start 0", "start 1"]
    # two compared push-tracked starts: both solved, the third not searched for
    est, calls = _fake_estimator(monkeypatch, [(50.0, 0.05), (40.0, 0.05), (5.0, 0.0)], compare=True, pushed=2)
    assert est.solve().objective == 40.0 and len(calls) == 2 and est.found == 2


def test_start_candidates_are_searched_one_at_a_time(monkeypatch):
    """iter_start_candidates_3d gives start_candidates_3d's starts, each found when asked
    for: the first needs the coarse grid and one refinement, not the later ones'."""
    import tacest.estimation.initial3d as initial3d

    run = _push_run()
    every = start_candidates_3d([run], 0.1, np.ones(3), 3)
    tracked = []
    real = initial3d.push_tracker_3d
    monkeypatch.setattr(initial3d, "push_tracker_3d", lambda r, e: tracked.append(len(e)) or real(r, e))
    found = initial3d.iter_start_candidates_3d([run], 0.1, np.ones(3), 3)
    first = next(found)
    assert first.label == every[0].label and np.array_equal(first.extents, every[0].extents)
    assert len(tracked) == 2  # the coarse grid, one refinement
    rest = list(found)
    assert [c.label for c in rest] == [c.label for c in every[1:]]
    for a, b in zip(rest, every[1:]):
        np.testing.assert_array_equal(a.extents, b.extents)
        assert a.inconsistency == b.inconsistency


def test_a_polytope_start_from_an_estimate_with_a_com_offset_has_the_shapes_own_radii():
    """An earlier polytope estimate with an estimated centre of mass: its vertices are
    the shape's less the offset d (Estimator3D.body_vertices); the start's radii are the
    shape's own, not those of the shifted vertices."""
    run = _push_run()
    shape = make_shape_3d("polytope:12")
    s = shape.initial(BOX / 0.1) * np.linspace(0.95, 1.05, shape.n_params)
    d = np.array([0.004, -0.003, 0.002])  # m
    est = _earlier_estimate(run, 150, shape="polytope:12")
    est.vertices = numeric_vertices_3d(shape, s, 0.1) - d
    est.params = {f"com_offset.d{a}": float(v) for a, v in zip("xyz", d)}
    start = estimator3d.previous_start([run], shape, est, 0.1)
    np.testing.assert_allclose(start.shape_params, s, rtol=1e-12)
    est.params = {}  # read as if at the centroid, the radii would be off by d·u_k
    assert not np.allclose(estimator3d.previous_start([run], shape, est, 0.1).shape_params, s, rtol=1e-3)

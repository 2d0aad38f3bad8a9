"""The experiment that decides (tacest.diagnosis.suggest): the expected discrimination
between candidate models' predictions and the search for the poke that maximizes it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from tacest.diagnosis import suggest as S
from tacest.diagnosis.diagnose import CandidateResult
from tacest.errors import TacestError

NOISE = {"force": 0.02, "normal": 0.02, "position": 1.0, "angle": 1.0}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A 2-D box poked twice by tacest's simulator, its plain estimate and the model state."""
    from tacest.dims import estimate_runs, record_sim
    from tacest.information.expected import ModelState
    from tacest.io.run import write_run
    from tacest.sim.record import SimOptions

    run = record_sim(SimOptions(dim=2, seed=3, pokes=2))
    path = tmp_path_factory.mktemp("suggest") / "run.h5"
    write_run(run, path)
    est = estimate_runs([run], "box")
    return SimpleNamespace(run=run, path=path, est=est, model=ModelState.from_estimate(est, [run]))


def _action(model, angle, style="dynamic"):
    from tacest.planning.actions import ActionSpace, object_height

    space = ActionSpace(n_fingers=1, style=style, object_height=object_height(model), up=np.asarray(model.up, float))
    lo, hi = space.bounds()
    u = (lo + hi) / 2
    u[0] = angle
    return space.action(0, u, model.centroid__world)


def test_discrimination_is_zero_for_one_model_and_symmetric(recorded):
    a = _action(recorded.model, math.radians(40))
    p0 = S.predicted_measurements(recorded.model, a, [], False)
    p1 = S.predicted_measurements(recorded.model, a, S.sim_effects_of("linear_drag", {"linear_drag.b": 1.0}), False)
    assert S.discrimination(p0, p0, NOISE) == 0.0
    assert S.discrimination(p0, p1, NOISE) == pytest.approx(S.discrimination(p1, p0, NOISE), rel=1e-12)


def test_a_force_bias_is_worth_its_known_log_likelihood_ratio(recorded):
    """Known answer: a bias b on every force sample and nothing else between two models
    is worth 0.5 T (b / sigma)² nats (the physics is the same: the bias is on the sensor)."""
    a = _action(recorded.model, math.radians(40))
    p0 = S.predicted_measurements(recorded.model, a, [], False)
    p1 = S.predicted_measurements(recorded.model, a, S.sim_effects_of("force_bias", {"force_bias.fx": 0.3,
                                                                                    "force_bias.fy": -0.1}), False)
    T, F = p0["contact"].shape
    want = 0.5 * T * F * (0.3 ** 2 + 0.1 ** 2) / NOISE["force"] ** 2
    assert S.discrimination(p0, p1, NOISE) == pytest.approx(want, rel=1e-9)


def test_the_suggestion_prefers_a_poke_that_separates_the_candidates(recorded):
    """A case built to need it: the plain model against strong linear drag (b = 1 N·s/m).
    A poke pressing straight down onto the box moves nothing, so drag changes nothing
    there (discrimination ~0); the search must choose a poke that moves the box, whose
    discrimination is orders of magnitude larger."""
    diag = SimpleNamespace(base=recorded.est, effects=[
        CandidateResult(name="linear_drag", kind="nlp", n_params=1, params={"linear_drag.b": 1.0})])
    down = _action(recorded.model, math.pi / 2)
    p0 = S.predicted_measurements(recorded.model, down, [], False)
    p1 = S.predicted_measurements(recorded.model, down, S.sim_effects_of("linear_drag", {"linear_drag.b": 1.0}),
                                  False)
    d_down = S.discrimination(p0, p1, NOISE)
    assert d_down < 1.0
    found = S.suggest(diag, [recorded.run], n=2, seed=1)
    assert len(found) == 2 and found[0].models == ["none", "linear_drag"]
    best = found[0].pairwise["none vs linear_drag"]
    assert best > 100.0 and best > 100 * d_down
    assert abs(found[0].plan.chosen_dict()["approach_angle"] - math.pi / 2) > math.radians(10)
    # best first, and the plan's own scores say so
    assert found[0].plan.scores.max() == pytest.approx(math.log1p(best), rel=1e-9)


def test_candidates_without_a_prediction_are_left_out_and_none_left_is_an_error(recorded):
    from tacest.errors import TacestError

    diag = SimpleNamespace(base=recorded.est, effects=[
        CandidateResult(name="time_scale", kind="transform", n_params=1, params={"scale": 1.05})])
    with pytest.raises(TacestError, match="nothing to tell apart"):
        S.suggest(diag, [recorded.run], n=1)
    with pytest.raises(TacestError, match="missing"):
        S.sim_effects_of("restitution", {})


def test_diagnose_suggest_writes_plan_files_through_the_cli(recorded, tmp_path):
    from tacest.io.plan import read_plan

    out = subprocess.run([sys.executable, "-m", "tacest", "diagnose", str(recorded.path), "--effects", "linear_drag",
                          "--max-folds", "2", "--fit-iterations", "40", "--suggest", "1", "-o", str(tmp_path / "d"),
                          "--json", "--quiet"], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    if not any(c["name"] == "linear_drag" and c["status"] == "ok" for c in d["effects"]):
        pytest.skip("the drag candidate's fit did not succeed on this short run")
    assert d["suggestions"][0]["file"] == "suggest_1.h5"
    plan = read_plan(tmp_path / "d" / "suggest_1.h5")
    assert plan.method == "discriminate" and plan.score == "expected_llr"
    assert "Suggested next experiments" in (tmp_path / "d" / "report.md").read_text()
    saved = json.loads((tmp_path / "d" / "diagnosis.json").read_text())
    assert saved["suggestions"] == d["suggestions"]


def test_diagnose_explore_decides_with_a_suggested_poke(tmp_path):
    """The closed loop on a case built to need it: a box with strong linear drag
    (b = 2 N·s/m) poked twice at random (gentle, slow pokes: drag hides, verdict none);
    one suggested poke (dynamic: the box slides fast) and the verdict names the drag.
    Candidates restricted to drag and a force bias, 2 folds and 40 iterations: cheap.
    Each diagnosis' fits run on a local cluster of 2 worker processes (--workers: the
    loop's results do not depend on where its fits run)."""
    out = subprocess.run([sys.executable, "-m", "tacest", "diagnose", "--explore", "--inject", "linear_drag:b=2.0",
                          "--seed", "3", "--pokes", "2", "--budget", "1", "--effects", "linear_drag,force_bias",
                          "--max-folds", "2", "--fit-iterations", "40", "-o", str(tmp_path / "x"), "--json", "--quiet",
                          "--workers", "2"],
                         capture_output=True, text=True, timeout=1200)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    steps = summary["steps"]
    assert summary["injected"] == [{"name": "linear_drag", "b": 2.0}] and summary["workers"] == 2
    assert steps[0]["verdict"] == "none" and steps[0]["next_action"]
    assert (tmp_path / "x" / "plan_1.h5").is_file() and (tmp_path / "x" / "diagnosis_0" / "report.md").is_file()
    assert steps[-1]["actions"] == 1 and steps[-1]["verdict"] == "linear_drag" and summary["decided"] is True
    assert (tmp_path / "x" / "candidates.png").is_file()
    from tacest.io.plan import read_plan

    assert read_plan(tmp_path / "x" / "plan_1.h5").method == "discriminate"


def test_diagnose_explore_refuses_runs_and_needs_runs_otherwise(recorded, tmp_path):
    for args, fragment in (([str(recorded.path), "--explore"], "give no RUNS"), ([], "needs RUNS")):
        out = subprocess.run([sys.executable, "-m", "tacest", "diagnose", *args, "-o", str(tmp_path / "y")],
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 2 and fragment in out.stderr and "Traceback" not in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1


def test_the_suggestion_works_in_3d_and_skips_what_it_cannot_predict():
    """3-D (the MuJoCo world): the plain model against strong drag on a box whose poses
    are observed; edge_radius (a tacest extension the simulator has no effect for) is
    left out.  The chosen poke separates the two by far more than a press straight down
    onto the box."""
    from tacest.dims import record_sim
    from tacest.estimation.config import EstimatorConfig
    from tacest.estimation.estimator3d import estimate_3d
    from tacest.information.expected3d import ModelState3
    from tacest.planning.actions import ActionSpace3, object_height
    from tacest.sim.record import SimOptions

    run = record_sim(SimOptions(dim=3, seed=1, pokes=2, fingers=1, observe_pose=0.0005, poke_style="dynamic"))
    est = estimate_3d([run], "box")
    diag = SimpleNamespace(base=est, effects=[{"name": "edge_radius"}, {"name": "linear_drag"}],
                           fits={"linear_drag": SimpleNamespace(params={"linear_drag.b": 2.0}),
                                 "edge_radius": SimpleNamespace(params={"edge_radius": 0.002})})
    found = S.suggest(diag, [run], n=1, iterations=2, population=8)
    assert found[0].models == ["none", "linear_drag"]
    best = found[0].pairwise["none vs linear_drag"]
    model = ModelState3.from_estimate(est, [run], EstimatorConfig())
    space = ActionSpace3(p_finger__world=model.p_finger__world, n_fingers=1, style="dynamic",
                         object_height=object_height(model), up=np.asarray(model.up, float))
    lo, hi = space.bounds()
    u = (lo + hi) / 2
    u[space.names.index("approach_elevation")] = math.pi / 2
    down = space.action(0, u, model.centroid__world)
    drag = S.sim_effects_of("linear_drag", {"linear_drag.b": 2.0}, 3)
    noise = {"force": 0.02, "normal": 0.02, "position": run.sigma_position, "angle": run.sigma_angle}
    d_down = S.discrimination(S.predicted_measurements(model, down, [], True),
                              S.predicted_measurements(model, down, drag, True), noise)
    assert best > 10 * max(d_down, 1.0)
    # nothing shows: screening draws the 3-D effects (a face friction per face of the box)
    blind = SimpleNamespace(base=est, verdict="none", fits={},
                            effects=[{"name": n} for n in ("edge_radius", "linear_drag", "face_friction", "com_offset")])
    screened = S.suggest(blind, [run], n=1, iterations=1, population=4)[0]
    assert screened.criterion == S.SCREEN and screened.models == ["none", "linear_drag", "face_friction", "com_offset"]
    assert all(np.isfinite(v) and v > 0 for v in screened.pairwise.values())


def test_diagnose_explore_in_3d_writes_its_loop(tmp_path):
    """The 3-D loop (MuJoCo, one finger, touch alone): a clean box, two random pokes,
    at most one added poke; the loop's files and summary are what the 2-D loop writes
    (whether a clean recording is blamed is the benchmark's question, not this test's:
    one candidate and 40 iterations)."""
    out = subprocess.run([sys.executable, "-m", "tacest", "diagnose", "--explore", "--dim", "3", "--inject", "none",
                          "--seed", "1", "--pokes", "2", "--budget", "1", "--effects", "force_bias",
                          "--fit-iterations", "40", "-o", str(tmp_path / "x"), "--json", "--quiet"],
                         capture_output=True, text=True, timeout=1500)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    steps = summary["steps"]
    assert summary["options"]["dim"] == 3 and summary["injected"] == [{"name": "none"}]
    assert summary["options"]["observe_pose"] is None
    assert set(steps[0]["candidates"]) == {"force_bias"}
    assert (tmp_path / "x" / "diagnosis_0" / "report.md").is_file() and (tmp_path / "x" / "candidates.png").is_file()
    if not summary["decided"] or len(steps) == 2:
        assert len(steps) == 2 and steps[0]["next_action"] and (tmp_path / "x" / "plan_1.h5").is_file()


def test_options_of_the_other_mode_are_refused_in_one_line(recorded, tmp_path):
    for args, fragment in ((["--explore", "--window", "5"], "--window: not an option of --explore"),
                           (["--explore", "--cold-starts", "none"], "--cold-starts: not an option of --explore"),
                           (["--explore", "--screen-by-fit"], "--screen-by-fit: not an option of --explore"),
                           ([str(recorded.path), "--budget", "3"], "--budget: not an option of a diagnosis of RUNS"),
                           ([str(recorded.path), "--observe-pose", "5e-4"],
                            "--observe-pose: not an option of a diagnosis of RUNS")):
        out = subprocess.run([sys.executable, "-m", "tacest", "diagnose", *args, "-o", str(tmp_path / "z")],
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 2 and fragment in out.stderr and len(out.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "z").exists()


def test_an_unknown_injected_effect_is_refused_before_the_folder_is_made(tmp_path):
    out = subprocess.run([sys.executable, "-m", "tacest", "diagnose", "--explore", "--inject", "wobble",
                          "-o", str(tmp_path / "w")], capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "unknown effect 'wobble'" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "w").exists()


#: the comparison, run in a fresh interpreter: a test process may hold threads (of
#: earlier tests), where tacest.parallel.fork_processes rightly refuses to fork
_FORK_SCRIPT = """
import sys
from types import SimpleNamespace
import numpy as np
import tacest.parallel
from tacest.diagnosis import suggest as S
from tacest.diagnosis.diagnose import CandidateResult
from tacest.dims import estimate_runs
from tacest.io.run import read_run

run = read_run(sys.argv[1])
diag = SimpleNamespace(base=estimate_runs([run], "box"), effects=[
    CandidateResult(name="linear_drag", kind="nlp", n_params=1, params={"linear_drag.b": 1.0})])
assert tacest.parallel.fork_processes(0, 6) >= 2, "a fresh process on Linux with 2 or more cores must fork"
forked = S.suggest(diag, [run], n=1, seed=2, iterations=2, population=6)
tacest.parallel.fork_processes = lambda workers, jobs: 1
here = S.suggest(diag, [run], n=1, seed=2, iterations=2, population=6)
print(np.array_equal(forked[0].plan.candidates, here[0].plan.candidates)
      and np.array_equal(forked[0].plan.scores, here[0].plan.scores), len(here[0].plan.scores))
"""


def test_the_suggestion_is_the_same_scored_in_forked_workers_or_here(recorded):
    """The search's candidates scored by forked copies of the process (the default where
    forking is safe) give the suggestion that this process alone gives."""
    import os

    if not sys.platform.startswith("linux") or (os.cpu_count() or 1) < 2:
        pytest.skip("the suggestion forks its workers on Linux with 2 or more cores only")
    res = subprocess.run([sys.executable, "-c", _FORK_SCRIPT, str(recorded.path)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split("\n")[0] == "True 12", res.stdout


ALL_CANDIDATES = ("restitution", "angular_damping", "linear_drag", "soft_contact", "force_bias", "force_scale",
                  "latency", "face_friction", "com_offset", "time_scale")


def _nothing_shows(est, names, known_mass=False, params=None):
    """A diagnosis whose verdict is ``none`` with the given candidates (fitted
    parameters ``params``: name -> dict)."""
    params = params or {}
    return SimpleNamespace(base=est, verdict="none", mass_prior={"known": known_mass},
                           effects=[CandidateResult(name=n, kind="nlp", n_params=1, params=params.get(n, {}))
                                    for n in names])


def test_screening_draws_every_predictable_candidate_from_its_typical_range(recorded):
    """Verdict none: every candidate compared is drawn SCREEN_DRAWS times from the
    simulator's typical range for the estimated object (drag b = m/τ, τ in 0.2-1 s:
    m <= b <= 5 m), seeded; force_scale (a mass without a known one) and time_scale
    (no prediction) are left out and said so; an unavailable candidate is not drawn."""
    diag = _nothing_shows(recorded.est, ALL_CANDIDATES)
    diag.effects[0].status = "unavailable"  # restitution
    assert S.criterion_for(diag) == S.SCREEN
    models, skipped = S.screening_models(diag, recorded.model, 2, seed=5)
    assert [m for m, _ in models] == ["none", "angular_damping", "linear_drag", "soft_contact", "force_bias",
                                      "latency", "face_friction", "com_offset"]
    assert sorted(n for n, _ in skipped) == ["force_scale", "time_scale"]
    assert all(len(sets) == S.SCREEN_DRAWS for _, sets in models[1:])
    m = recorded.model.mass
    for (eff,) in dict(models)["linear_drag"]:
        assert m - 1e-12 <= eff["b"] <= 5 * m + 1e-12
    for (eff,) in dict(models)["face_friction"]:
        assert len(eff["values"]) == len(recorded.model.vertices)
    again, _ = S.screening_models(diag, recorded.model, 2, seed=5)
    other, _ = S.screening_models(diag, recorded.model, 2, seed=6)
    assert repr(again) == repr(models) and repr(other) != repr(models)
    known, skipped = S.screening_models(_nothing_shows(recorded.est, ALL_CANDIDATES, known_mass=True),
                                        recorded.model, 2, seed=5)
    assert "force_scale" in dict(known) and [n for n, _ in skipped] == ["time_scale"]
    blamed = SimpleNamespace(**{**vars(diag), "verdict": "linear_drag"})
    assert S.criterion_for(blamed) == S.SEPARATE


def test_while_nothing_shows_the_suggestion_aims_at_effects_of_typical_size_not_at_noise(recorded):
    """A case built to need screening: the data show nothing, so the candidates' fitted
    sizes are noise (drag b = 1e-6 N·s/m, damping c = 1e-9 N·m·s).  Separating those
    fits is worth almost nothing whatever the poke (< 1 nat: the old criterion aimed at
    noise); the screening poke would show a drag of typical size by at least the
    detection level SCREEN_DETECT, more than ten times what a poke pressing straight down
    on the box shows."""
    noise_sized = {"linear_drag": {"linear_drag.b": 1e-6}, "angular_damping": {"angular_damping.c": 1e-9}}
    diag = _nothing_shows(recorded.est, ("linear_drag", "angular_damping"), params=noise_sized)
    separated = S.suggest(diag, [recorded.run], n=1, seed=1, criterion=S.SEPARATE)[0]
    assert separated.criterion == S.SEPARATE and min(separated.pairwise.values()) < 1.0
    screened = S.suggest(diag, [recorded.run], n=1, seed=1)[0]
    assert screened.criterion == S.SCREEN and screened.plan.extra_attrs["criterion"] == S.SCREEN
    assert screened.models == ["none", "linear_drag", "angular_damping"]
    assert set(screened.pairwise) == {"none vs linear_drag", "none vs angular_damping"}
    models, _ = S.screening_models(diag, recorded.model, 2, seed=1)

    def shows_drag(action):
        p0 = S.predicted_measurements(recorded.model, action, [], False)
        return np.mean([S.discrimination(p0, S.predicted_measurements(recorded.model, action, eff, False), NOISE)
                        for eff in dict(models)["linear_drag"]])

    chosen = shows_drag(screened.plan.chosen)
    assert chosen >= S.SCREEN_DETECT and chosen > 10 * shows_drag(_action(recorded.model, math.pi / 2))
    with pytest.raises(TacestError, match="unknown suggestion criterion"):
        S.suggest(diag, [recorded.run], criterion="sreen")


def test_screening_ties_go_to_the_poke_whose_weakest_effect_shows_most(recorded, monkeypatch):
    """Every searched poke shows every drawn effect above the detection level (a stand-in
    discrimination of 10 + 100 × speed nats), so the capped scores tie; the tie-break
    (SCREEN_TIE_WEIGHT × log(1 + the smallest discrimination)) must pick the fastest
    searched poke, not the first one found."""
    diag = _nothing_shows(recorded.est, ("linear_drag", "angular_damping"))
    from tacest.sim.pokes import POKE_NAMES

    speed = POKE_NAMES.index("speed")
    monkeypatch.setattr(S, "predicted_measurements", lambda model, action, eff, has_pose: {"action": action})
    monkeypatch.setattr(S, "discrimination", lambda a, b, noise: 10.0 + 100.0 * float(b["action"][speed]))
    found = S.suggest(diag, [recorded.run], n=1, seed=2)[0]
    speeds = found.plan.candidates[:, speed]
    assert found.plan.chosen[speed] == pytest.approx(speeds.max())
    assert found.plan.scores.max() > math.log1p(S.SCREEN_DETECT)

"""The claims users rely on, each tested end to end with the real estimator (no stand-in,
nothing read from /truth by the code under test; /truth only grades the answer):

- the diagnosis names a strong injected effect and says ``none`` on the clean twin of
  the same recording (the same object and pokes);
- the EIG planner beats the random baseline on a case built so that it must: a tall
  box whose top face, the one part of it the data so far do not fix, only a steep poke
  can reach, and the random baseline never draws one;
- the estimator's known answer over several seeds, the hard ones included, as a median
  and a worst case.

Each is cheap enough for CI (short recordings, few candidates); the ones above 30 s are
marked slow.  Wall times measured on the 2-core test machine under load are in each
docstring.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tacest.diagnosis import diagnose as diag_mod
from tacest.estimation.config import EstimatorConfig
from tacest.io.run import write_run
from tacest.sim.record import SimOptions, initial_state, record_sim, simulate_aimed_pokes

TACEST = str(Path(sys.executable).parent / "tacest")

# ------------------------------------------------------------------------------------
# the diagnosis names what was injected, and nothing on a clean twin

#: the recording of the diagnosis claims: a box (seed 3, 11 x 9 cm, 0.41 kg) poked
#: twice at random; two pokes are two held-out pieces, two folds
DIAG_SEED, DIAG_POKES = 3, 2
#: candidates of every diagnosis below: one NLP augmentation and one data transform, so
#: that the verdict is a choice between the kinds, each fitted for real
DIAG_CANDIDATES = ("force_bias", "latency")


def _diagnosis_recording(effects):
    return record_sim(SimOptions(object_spec="box", seed=DIAG_SEED, pokes=DIAG_POKES, effects=list(effects)))


def _diagnose(run):
    """diagnose() of a run without its /truth (nothing to read the answer from)."""
    bare = run.replace(truth=None)
    return diag_mod.diagnose([bare], "box", options=diag_mod.DiagnoseOptions(effects=DIAG_CANDIDATES))


@pytest.mark.slow
def test_diagnosis_names_a_force_bias_and_says_none_on_its_clean_twin():
    """A force-sensor zero offset of (0.3, -0.2) N (15-20 times the force noise, 0.02 N,
    on every sample with or without contact; the simulator draws 0.1-0.4 N) is blamed on
    force_bias, which closes the held-out gap and gives the offset back; the same
    recording without the offset (the same object, pokes and noise: a sensor effect
    leaves the physics as it is) is blamed on nothing.  Measured: force_bias closes
    100 % of a gap of 7162 (folds 2 of 2), offset within 1e-4 N; on the clean twin no
    candidate beats its penalty (latency's best improvement 0.4 against 3.0).  ~40 s
    (60 s under a load of 4 on 2 cores)."""
    biased = _diagnosis_recording(["force_bias:fx=0.3,fy=-0.2"])
    d = _diagnose(biased)
    assert d.verdict == "force_bias", d.reason
    fb = next(c for c in d.effects if c.name == "force_bias")
    got = np.array([fb.params["force_bias.fx"], fb.params["force_bias.fy"]])
    # 10 % of the offset as a vector: what a sensor zero must be known to (the offset is
    # seen on every free sample, 0.3 N against a noise of 0.02 N; measured 0.003 %)
    assert np.linalg.norm(got - [0.3, -0.2]) <= 0.1 * math.hypot(0.3, 0.2), fb.params
    # it explains the recording: at least 90 % of the plain model's held-out gap closed
    # (what is left is the floor's own scatter)
    assert fb.reduction >= 0.9, (fb.reduction, fb.gap_before, fb.gap_after)
    assert fb.folds_improved == fb.folds_compared == DIAG_POKES

    clean = _diagnose(_diagnosis_recording([]))
    assert clean.verdict == "none", clean.reason
    assert not any(c.significant for c in clean.effects), [c.to_json() for c in clean.effects]
    # every candidate was compared (a "none" that compared nothing would be "undetermined")
    assert all(c.status == "ok" for c in clean.effects), [(c.name, c.status, c.message) for c in clean.effects]


@pytest.mark.slow
def test_tacest_diagnose_names_a_long_tactile_latency(tmp_path):
    """An 8-sample (80 ms) tactile delay, outside the first versions' latency grid
    (1-5), through the command line: ``tacest diagnose --json`` blames latency and keeps
    the delay within one sample (a flag covers the interval (t-1, t]: docs/diagnosis.md,
    "Latency's k").  Measured: k = 8, the whole held-out gap closed.  ~30 s (50 s under
    a load of 4 on 2 cores)."""
    run = _diagnosis_recording(["latency:samples=8"])
    path = tmp_path / "latency.h5"
    write_run(run, path, include_truth=False)
    # latency alone: the choice between an augmentation and a transform on this
    # recording is the claim above; here the command line and the delay's size
    res = subprocess.run([TACEST, "diagnose", str(path), "--effects", "latency", "--json", "--quiet",
                          "-o", str(tmp_path / "report")], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["verdict"] == "latency", out["reason"]
    lat = next(e for e in out["effects"] if e["name"] == "latency")
    assert abs(lat["params"]["samples"] - 8) <= 1, lat
    assert lat["reduction"] >= 0.5, lat  # it explains most of what the plain model leaves


# ------------------------------------------------------------------------------------
# EIG beats random where it must

#: a tall box (4 x 13 cm) on a slippery ground (seed 16: mu 0.24, 0.92 kg, which slides
#: rather than tips under the pokes below), weighed (mass known to 2 %, so that ground
#: friction follows from the sliding force)
PLAN_OBJECT, PLAN_SEED = "box:0.04,0.13", 16
PLAN_HEIGHT = 0.13


def _side_poke(i, state):
    """Poke i of the history: low on a side face (a quarter of the height below the
    centroid), from the right and the left alternately, flat (12 deg) then steeper
    (45 deg, so that the finger slides along the face and its friction is seen): the
    box slides; its sides, mass and frictions become known, its height does not (no
    touch reaches the top, and a sliding box does not show where its top is)."""
    world = state.world()
    c, v = world.centroid__world(), world.vertices__world()
    elev = math.radians((12.0, 12.0, 45.0, 45.0)[i])
    angle = elev if i % 2 == 0 else math.pi - elev
    target = c + np.array([0.0, -0.25 * float(np.ptp(v[:, 1]))])
    depth = 0.02
    return np.array([0.0, angle, target[0], target[1], depth, (0.02 + depth) / 1.0])


def _reaches_top(run, segment) -> float:
    """Largest upward component of the contact normal in one poke: ~0 for a side face,
    1 for the top face, in between at the top corners (which also tell the height)."""
    a, b = segment
    c = run.contact[a:b, 0].astype(bool)
    return float(np.max(run.normal[a:b, 0][c, 1])) if c.any() else -1.0


@pytest.mark.slow
def test_eig_plans_the_poke_that_teaches_the_unknown_height_and_random_cannot():
    """Four low side pokes of a tall weighed box leave its height unknown (the estimate's
    height is the start's guess).  The EIG planner (shipped settings) chooses a steep poke
    that, executed on the true object, reaches the top face; the random baseline (the
    simulator's random approach angles, 10-65 deg from either side, aimed at the centroid)
    never reaches it, on 6 seeds out of 6.  After the poke and a new estimate, the height
    is known to 3 mm (the issue's shape target) with EIG's poke and is worse with a
    random one.  Measured: EIG's poke at 107.5 deg touches the top (normal 0.81 up),
    height error 0.1 mm; random pokes 16-18 mm off (the height stays the start's guess).
    ~35 s (60 s under a load of 4 on 2 cores)."""
    from tacest.dims import estimate_runs
    from tacest.planning.planner import PlanSettings, plan_next

    opts = SimOptions(object_spec=PLAN_OBJECT, seed=PLAN_SEED, pokes=0)
    history = simulate_aimed_pokes(_side_poke, 4, opts, state=initial_state(opts))
    cfg = EstimatorConfig().updated({"prior": {"mass": float(history.truth.mass), "mass_log_sigma": 0.02}})
    est = estimate_runs([history], "box", config=cfg)

    def execute(poke):
        run = simulate_aimed_pokes(lambda i, st: poke, 1, opts, run=history)
        return run, _reaches_top(run, run.actions.segments[-1])

    def height_error(run):
        after = estimate_runs([run], "box", config=cfg)
        return abs(float(np.ptp(np.asarray(after.vertices)[:, 1])) - PLAN_HEIGHT)

    eig = plan_next(est, [history], PlanSettings(method="eig", seed=0))
    eig_run, eig_up = execute(eig.chosen)
    # 0.5: a normal at least 30 deg from the side faces' (the top face or a top corner)
    assert eig_up > 0.5, (math.degrees(eig.chosen[1]), eig_up)
    randoms = []
    for seed in range(6):
        plan = plan_next(est, [history], PlanSettings(method="random", seed=seed))
        run, up = execute(plan.chosen)
        # the case is as built: no random poke reaches the top face or its corners
        assert up < 0.5, (seed, math.degrees(plan.chosen[1]), up)
        randoms.append(run)
    eig_err = height_error(eig_run)
    assert eig_err <= 3e-3, eig_err
    assert height_error(randoms[0]) > eig_err


# ------------------------------------------------------------------------------------
# the estimator's known answer over seeds


#: seeds of the 6-poke box recordings (docs/estimation.md's benchmark case): 0-4 hold the
#: hard ones (0: the mass-friction valley, 4 pushes from one side at one height; 3: a
#: light box; 4: the light-object collapse, mass 0.008 kg for 0.23)
KNOWN_ANSWER_SEEDS = (0, 1, 2, 3, 4)


@pytest.mark.slow
def test_estimator_known_answer_over_seeds_median_and_worst_case():
    """Six random pokes of a box, default sensor noise, seeds 0-4 with their hard cases.
    The placed shape's Chamfer distance: median within the issue's 3 mm, worst within
    15 mm (a fit in a wrong basin of the shape, the pitfalls' box twice too long, is off
    by several cm; the data of seed 0 leave a valley along which an older estimator put
    the box 12 mm off, docs/estimation.md).  What slow pushes identify, the ground
    friction times the mass (mu (m g + push)), within 15 % on at least four of the five
    (the fifth may be the light-object collapse, a documented limitation:
    docs/estimation.md, "Pose observations and light objects"), and the finger friction
    within 15 % on the median.  Measured: Chamfer 0.20, 0.31, 1.51, 1.22, 7.48 mm
    (median 1.22); mu x m within 2-7 % but on seed 4 (-75 %).  ~50 s (80 s under a load
    of 4 on 2 cores)."""
    from tacest.dims import estimate_runs
    from tacest.evaluation.metrics import evaluate

    chamfer, mu_m, mu_f = [], [], []
    for seed in KNOWN_ANSWER_SEEDS:
        run = record_sim(SimOptions(object_spec="box", seed=seed, pokes=6))
        est = estimate_runs([run], "box")
        assert est.success, (seed, est.solver_status)
        chamfer.append(evaluate(est, run)["chamfer"])
        tr = run.truth
        mu_m.append(est.params["friction_ground"] * est.params["mass"] / (tr.friction_ground * tr.mass) - 1.0)
        mu_f.append(est.params["friction_finger"] / tr.friction_finger - 1.0)
    chamfer, mu_m, mu_f = map(np.asarray, (chamfer, mu_m, mu_f))
    assert np.median(chamfer) <= 3e-3, chamfer
    assert np.max(chamfer) <= 15e-3, chamfer
    assert np.sum(np.abs(mu_m) <= 0.15) >= len(KNOWN_ANSWER_SEEDS) - 1, mu_m
    assert np.median(np.abs(mu_f)) <= 0.15, mu_f

"""tacest diagnose: noise-floor statistics, run slicing, the data-transform candidates,
the whole pipeline on a cheap stand-in of the estimator, the JSON schema, failure paths,
and (slow) latency recovery with the real estimator.

The pipeline tests replace the estimator's fits by a stand-in (``_StandIn``) whose
residuals come from the recording's truth geometry: the contact-flag residual of every
finger, which a tactile latency disturbs, plus fixed whitened noise on the other terms.
It runs in milliseconds, so the folds, the candidate choice, the verdict, the report and
the JSON are tested end to end; a real estimate of a 3-poke run takes 20-100 s here.
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
from tacest.diagnosis.candidates import candidate, parse_effect_list
from tacest.diagnosis.fitting import FitResult, occam_objective
from tacest.estimation.floor import (TERMS, contact_windows, fit_floor, flagged_windows,
                                    residual_dof, window_tests)
from tacest.diagnosis.heldout import make_folds, make_pieces
from tacest.io.slicing import join_runs, slice_run, slice_run_estimate, split_at_actions
from tacest.diagnosis.transforms import undo_latency, undo_time_scale
from tacest.errors import TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.initial import finger_gaps
from tacest.io.estimate import Estimate, RunEstimate, write_estimate
from tacest.io.h5util import sha256_file
from tacest.io.run import write_run
from tacest.sim.record import SimOptions, record_sim

TACEST = str(Path(sys.executable).parent / "tacest")
#: m, the estimator's default contact-gap sigma (tacest/configs/estimate.toml noise.contact_gap)
SIGMA_GAP = 5e-4


# ------------------------------------------------------------------------------------
# synthetic whitened residuals


def _synthetic(rng, n_runs=2, T=600, K=4, F=1, excess=None, level=1.0):
    """Residuals (0.5·‖r‖²) of pure whitened noise at ``level`` (its variance per degree
    of freedom) with the dof of residual_dof, for runs with alternating contact phases
    of 70 samples; ``excess`` = (run, start, stop, term, amount) adds ``amount`` (‖r‖²
    units) spread over the window.  (residuals, dofs, states) as tacest.estimation.floor
    takes."""
    residuals, dofs, states = [], [], []
    for i in range(n_runs):
        state = (np.arange(T) // 70) % 2 == 1
        dof = {t: np.zeros(T) for t in TERMS}
        dof["force"][1:] = 2 * F
        dof["normal"][1:] = state[1:] * F
        dof["contact"][:] = F
        dof["dynamics"][:] = 3
        dof["penetration"][:] = K
        dof["complementarity"][1:] = K
        dof["dissipation"][1:] = F
        dof["cone"][1:] = 2 * F
        res = {t: 0.5 * level * rng.chisquare(np.maximum(d, 1e-12)) * (d > 0) for t, d in dof.items()}
        if excess is not None and excess[0] == i:
            _, a, b, term, amount = excess
            res[term][a:b] += 0.5 * amount / (b - a)
        residuals.append(res)
        dofs.append(dof)
        states.append(state)
    return residuals, dofs, states


@pytest.mark.parametrize("mode", ["nominal", "calibrated"])
def test_pure_noise_flags_at_most_the_stated_false_alarm_rate(mode):
    # family-wise false-alarm rate alpha = 0.1 over 120 independent synthetic diagnoses:
    # the flagged fraction is binomial(120, <= 0.1): mean <= 12, sd ~3.3; allowing 0.1 +
    # 3 sd (0.182) keeps this test from failing by chance while catching a broken test
    # (an uncorrected test at alpha 0.1 flags nearly every diagnosis)
    rng = np.random.default_rng(0)
    alpha, trials = 0.1, 120
    hits = 0
    for _ in range(trials):
        res, dofs, states = _synthetic(rng, T=420)
        floor = fit_floor(res, dofs, states, mode=mode)
        stats = window_tests(res, dofs, states, floor, alpha=alpha)
        hits += any(s.flagged for s in stats)
    assert hits / trials <= alpha + 3 * np.sqrt(alpha * (1 - alpha) / trials), hits


def test_pure_noise_floor_is_the_nominal_level():
    rng = np.random.default_rng(1)
    res, dofs, states = _synthetic(rng, n_runs=3)
    floor = fit_floor(res, dofs, states)
    for key, mu in floor.mu.items():
        # whitened noise: level 1 per degree of freedom; the median estimate over ~25
        # windows has a relative sd of ~0.1, and the cap at 1 only lowers it
        assert 0.75 <= mu <= 1.0, (key, mu)
        assert floor.phi[key] < 1.35, (key, floor.phi[key])


@pytest.mark.parametrize("mode", ["nominal", "calibrated"])
def test_injected_excess_is_flagged_with_most_of_the_share(mode):
    rng = np.random.default_rng(2)
    # 300 extra units of ‖r‖² in the dynamics residual of one 20-sample window (60 dof):
    # ~25 sigma of a chi-square with 60 dof
    res, dofs, states = _synthetic(rng, excess=(1, 145, 160, "dynamics", 300.0))
    floor = fit_floor(res, dofs, states, mode=mode)
    stats = window_tests(res, dofs, states, floor, alpha=0.01)
    where = flagged_windows(stats)
    assert where, "the injected window is not flagged"
    top = where[0]
    assert (top.run, top.term) == (1, "dynamics")
    assert top.start <= 145 and top.stop >= 160 - 5  # windows are cut at contact changes
    assert top.share > 0.5
    # nothing else is flagged far from it
    assert all(s.run == 1 and s.term == "dynamics" for s in where)


def test_contact_windows_tile_and_respect_states():
    state = np.array([0] * 45 + [1] * 7 + [0] * 3, bool)
    wins = contact_windows(state, window=20)
    assert wins[0][0] == 0 and wins[-1][1] == len(state)
    assert all(a < b for a, b, _ in wins)
    assert all(w1[1] == w2[0] for w1, w2 in zip(wins, wins[1:]))
    assert all(b - a <= 20 for a, b, _ in wins)
    for a, b, c in wins:
        assert np.all(state[a:b] == c)


# ------------------------------------------------------------------------------------
# recordings


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """Short simulated recordings (3 pokes): clean, and with a 2-sample tactile latency."""
    folder = tmp_path_factory.mktemp("diag")
    out = {}
    for name, effects in (("none", []), ("latency", ["latency:samples=2"])):
        run = record_sim(SimOptions(seed=3, pokes=3, effects=effects))
        path = folder / f"{name}.h5"
        write_run(run, path)
        out[name] = path
    return out


def _read(path):
    from tacest.io.run import read_run

    return read_run(path)


def test_slicing_round_trip(recordings):
    run = _read(recordings["latency"])
    parts = split_at_actions(run)
    assert len(parts) == 3
    for p in parts:
        p.validate()
        assert p.actions.segments[0, 0] == 0
    joined = join_runs(parts)
    for name in ("time", "finger_position", "contact", "force", "normal"):
        np.testing.assert_array_equal(getattr(joined, name), getattr(run, name))
    np.testing.assert_array_equal(joined.actions.segments, run.actions.segments)
    np.testing.assert_array_equal(joined.truth.pose, run.truth.pose)
    sub = slice_run(run, 10, 50)
    assert sub.n_samples == 40 and np.array_equal(sub.contact, run.contact[10:50])
    with pytest.raises(TacestError):
        slice_run(run, 50, 51)


def test_slice_run_estimate_zeroes_the_first_impulse():
    T = 30
    re = RunEstimate(pose=np.arange(T * 3.0).reshape(T, 3), velocity=np.ones((T, 3)),
                     impulses={"finger_0": np.ones((T, 2))}, residuals={"force": np.arange(T, dtype=float)})
    s = slice_run_estimate(re, 5, 12)
    assert s.pose.shape == (7, 3) and s.pose[0, 0] == 15.0
    assert np.all(s.impulses["finger_0"][0] == 0) and np.all(s.impulses["finger_0"][1:] == 1)
    assert s.residuals["force"][0] == 5.0


def test_folds_hold_out_every_piece_once(recordings):
    run = _read(recordings["none"])
    pieces = make_pieces([run])
    folds = make_folds(pieces, max_folds=2)
    held = [p for f in folds for p in f.heldout]
    assert sorted(held, key=lambda p: p.start) == pieces
    for f in folds:
        assert not set(f.train) & set(f.heldout)
    assert make_folds(pieces[:1]) == []


def test_undo_latency_and_time_scale(recordings):
    run = _read(recordings["latency"])
    u = undo_latency(run, 2)
    np.testing.assert_array_equal(u.contact[:-2], run.contact[2:])
    np.testing.assert_array_equal(u.contact[-2:], np.repeat(run.contact[-1:], 2, axis=0))
    np.testing.assert_array_equal(u.finger_position, run.finger_position)
    u.validate()
    s = undo_time_scale(run, 1.04)
    assert s.dt == pytest.approx(run.dt / 1.04)
    np.testing.assert_allclose(np.diff(s.time), run.dt / 1.04)


def _walk(name, f, screening=None, budget=10):
    """The diagnosis' line search (diagnose._fit_candidate) on an objective f: the values
    fitted and the value kept (choose_transform_value)."""
    from tacest.diagnosis.candidates import (TRANSFORM_IDENTITY, choose_transform_value, first_transform_values,
                                             next_transform_value)

    ident = TRANSFORM_IDENTITY[name]
    objs = {ident: f(ident)}
    queue = first_transform_values(name, screening)
    fitted = []
    while len(fitted) < budget:
        v = queue.pop(0) if queue else next_transform_value(name, objs)
        if v is None:
            break
        objs[v] = f(v)
        fitted.append(v)
    return fitted, choose_transform_value(name, {k: o for k, o in objs.items() if k != ident})


def test_transform_line_search_walks_to_the_minimum():
    fitted, kept = _walk("latency", lambda k: 4 * (k - 4.0) ** 2, screening={1: 0.0, 2: 1.0, 3: 2.0})
    assert fitted == [1, 2, 3, 4, 5] and kept == 4  # stops once 4 is bracketed by 3 and 5
    fitted, kept = _walk("latency", lambda k: 4 * (k - 4.0) ** 2, screening={1: 0.0}, budget=3)
    assert kept == 3  # the budget ends the walk on the way
    fitted, kept = _walk("time_scale", lambda s: (s - 1.04) ** 2)
    assert fitted[:2] == [0.955, 1.045] and kept in (1.03, 1.045)
    fitted, kept = _walk("time_scale", lambda s: (s - 1.0) ** 2)
    assert kept in (0.985, 1.015)  # no clock error: the values next to 1 (the plain model is best)


def _hinge(true_k, slope, shelf):
    """A latency objective as measured on real fits (lat_profile in docs/diagnosis.md):
    falling by ``slope`` per sample up to the true delay, rising by ``shelf`` per sample
    beyond it (0.0-1.2 measured: a flag covers the interval (t-1, t], the shape absorbs
    part of a longer shift)."""
    return lambda k: 30.0 + slope * max(true_k - k, 0) + shelf * max(k - true_k, 0)


@pytest.mark.parametrize("shelf", [0.0, 0.1, 1.2])
@pytest.mark.parametrize("slope", [5.0, 20.0])
def test_latency_search_reaches_every_delay_of_the_grid_within_one_sample(slope, shelf):
    """Delays of 1 to 20 samples (50-200 ms of a camera-based tactile sensor at 100 Hz:
    candidates.TRANSFORM_GRIDS) are kept within one sample with the diagnosis' budget of
    three fits, the screening profile being the same objective at LATENCY_SCREEN (the
    quick fits see the same data); delays beyond the grid are kept at its end.  Slopes:
    measured 15-26 per sample on a 2-poke recording, 5 is a weaker effect.  The old
    walk (one grid step at a time from the start) reached 3 for a true 15."""
    from tacest.diagnosis.candidates import LATENCY_SCREEN, TRANSFORM_GRIDS

    grid_max = max(TRANSFORM_GRIDS["latency"])
    assert grid_max >= 20
    for true_k in list(range(1, grid_max + 1)) + [grid_max + 3]:
        f = _hinge(true_k, slope, shelf)
        fitted, kept = _walk("latency", f, screening={k: f(k) for k in LATENCY_SCREEN},
                             budget=diag_mod.FITS_PER_CANDIDATE)
        assert abs(kept - min(true_k, grid_max)) <= 1, (true_k, fitted, kept)


@pytest.mark.parametrize("true_s", [0.82, 0.85, 0.88, 0.90, 0.93, 0.95, 0.97, 0.99, 1.01, 1.03, 1.05, 1.07, 1.10, 1.12,
                                    1.15, 1.18])
def test_time_scale_search_reaches_every_clock_error_of_the_grid(true_s):
    """Clock errors to ±18 % (the grid's span; candidates.TRANSFORM_GRIDS) are kept within
    one and a half grid steps (2.25 %) with the diagnosis' budget of three fits, on a
    misfit that grows as the gravity seen, (s/s_true)^2 - 1, squared (quadratic near the
    minimum, steeper beyond: a parabola in s overshot 12 % by two steps; the search's is
    in s²)."""
    from tacest.diagnosis.candidates import TIME_SCALE_STEP

    f = lambda s: 2000.0 * ((s / true_s) ** 2 - 1.0) ** 2  # noqa: E731
    fitted, kept = _walk("time_scale", f, budget=diag_mod.FITS_PER_CANDIDATE)
    assert abs(kept - true_s) <= 1.5 * TIME_SCALE_STEP + 1e-9, (true_s, fitted, kept)


# ------------------------------------------------------------------------------------
# the pipeline on a stand-in estimator


class _StandIn:
    """Replaces fit_local / fit_estimator in tacest.diagnosis.diagnose (see module doc).

    Residuals: contact = 0.5 Σ_f [c (gap/σ)² + (1 - c) min(gap, 0)²/σ²] with the true
    geometry (gap at the nearer end of the flag's interval where c = 1): what a fit with
    the right shape and poses would leave; every other term 0.5·0.1·χ²(dof) from draws
    seeded by the piece, so the same for every candidate."""

    def __init__(self):
        self.calls = 0
        self.reaches = set()  # noise.complementarity_reach of every fit's configuration

    def fit_local(self, runs, shape, config, warm=None, warm_runs=None, pinned=None, pin="all", echo=None,
                  information=False, accept_budget=False, effects=()):
        self.calls += 1
        self.reaches.add(config.noise.complementarity_reach)
        tr = runs[0].truth
        V = np.asarray(tr.vertices, float)
        rests = []
        for run in runs:
            seed = run.n_samples * 100003 + int(run.extra_attrs.get("slice_start", 0))
            rng = np.random.default_rng(seed)
            dof = residual_dof(run, V.shape[0])
            # the same normal draws whatever the flags; a term sums as many squares as it has dof
            z2 = rng.normal(size=(len(TERMS), run.n_samples, 8)) ** 2
            csum = np.cumsum(np.concatenate([np.zeros((len(TERMS), run.n_samples, 1)), z2], axis=2), axis=2)
            res = {t: 0.05 * np.take_along_axis(csum[i], dof[t].astype(int)[:, None], axis=1)[:, 0]
                   for i, t in enumerate(TERMS)}
            gaps = finger_gaps(run, V, run.truth.pose) / SIGMA_GAP
            # a flag covers the interval (t-1, t] (SPEC): the nearer end counts
            g_int = np.minimum(gaps, np.vstack([gaps[:1], gaps[:-1]]))
            c = run.contact.astype(bool)
            res["contact"] = 0.5 * np.sum(np.where(c, g_int ** 2, np.minimum(gaps, 0) ** 2), axis=1)
            rests.append(RunEstimate(pose=run.truth.pose, velocity=np.zeros_like(run.truth.pose), residuals=res,
                                     source_file=run.filename or ""))
        est = Estimate(dim=2, shape="box", vertices=V,
                       params={"mass": tr.mass, "inertia": tr.inertia, "friction_ground": tr.friction_ground,
                               "friction_finger": tr.friction_finger},
                       runs=rests, solver_status="Solve_Succeeded", success=True, objective=0.0)
        return FitResult(estimate=est, runs=list(runs), theta=np.zeros(6))

    def fit_estimator(self, runs, shape, config, effects=()):
        return self.fit_local(runs, shape, config, effects=effects)


@pytest.fixture
def stand_in(monkeypatch):
    s = _StandIn()
    monkeypatch.setattr(diag_mod, "fit_local", s.fit_local)
    monkeypatch.setattr(diag_mod, "fit_estimator", s.fit_estimator)
    return s


def test_pipeline_blames_latency_and_recovers_it(recordings, stand_in):
    run = _read(recordings["latency"])
    d = diag_mod.diagnose([run], "box", options=diag_mod.DiagnoseOptions(effects=("latency", "time_scale")))
    assert d.verdict == "latency", d.reason
    lat = next(c for c in d.effects if c.name == "latency")
    assert lat.params == {"samples": 2}
    assert lat.reduction > 0.5
    assert lat.folds_improved == lat.folds_compared == 3
    # time scale changes nothing the stand-in sees: no improvement, not significant
    ts = next(c for c in d.effects if c.name == "time_scale")
    assert not ts.significant and abs(ts.improvement) < 1e-9 and abs(ts.full_improvement) < 1e-9
    # screened by its fit to all data (fit_screen) it is not held out, and the reason says so
    d = diag_mod.diagnose([run], "box", options=diag_mod.DiagnoseOptions(effects=("latency", "time_scale"),
                                                                         fit_screen=True))
    ts = next(c for c in d.effects if c.name == "time_scale")
    assert d.verdict == "latency" and ts.status == "screened" and not ts.heldout and "time_scale" in d.reason
    # where: the contact term carries the flagged excess
    assert d.where and d.where[0].term == "contact"


def test_pipeline_on_a_clean_recording_says_none(recordings, stand_in):
    run = _read(recordings["none"])
    d = diag_mod.diagnose([run], "box", options=diag_mod.DiagnoseOptions(effects=("latency", "time_scale")))
    assert d.verdict == "none", d.reason
    assert all(not c.significant for c in d.effects)
    # force_scale was not a candidate here: no caveat about it
    assert "force_scale" not in d.reason
    # the mass prior every fit used is reported: the configuration's weak default
    assert d.to_json()["mass_prior"] == {"mass": EstimatorConfig().prior.mass,
                                         "log_sigma": EstimatorConfig().prior.mass_log_sigma, "known": False}


def test_candidates_no_better_on_all_data_are_not_held_out(recordings, stand_in):
    """With fit_screen, a candidate whose fit to all data improves on the plain model's by
    less than its penalty is not held out (screened_by_fit): its held-out fits are skipped, the
    verdict is still decided (none, not undetermined), the reason and the JSON say why,
    and a suggestion still sees the candidate (suggest.ranked_candidates)."""
    from tacest.diagnosis.suggest import ranked_candidates

    run = _read(recordings["none"])
    opts = dict(effects=("latency", "time_scale"))
    d = diag_mod.diagnose([run], "box", options=diag_mod.DiagnoseOptions(fit_screen=True, **opts))
    screened_calls = stand_in.calls
    assert d.verdict == "none", d.reason
    assert all(diag_mod.screened_for_fit(c) and not c.heldout for c in d.effects)
    assert all(c.full_improvement < c.penalty for c in d.effects)
    assert "not held out" in d.reason and "not compared" not in d.reason
    js = d.to_json()
    assert js["options"]["fit_screen"] is True
    assert all(e["status"] == "screened" and e["full_improvement"] is not None for e in js["effects"])
    assert {name for name, _ in ranked_candidates(d)} == {"latency", "time_scale"}
    # held out with the screen off (the default): the same verdict from more fits
    stand_in.calls = 0
    d = diag_mod.diagnose([run], "box", options=diag_mod.DiagnoseOptions(**opts))
    assert d.verdict == "none" and all(c.status == "ok" and c.heldout for c in d.effects)
    assert stand_in.calls > screened_calls


def test_screened_by_fit_is_bic_on_all_data():
    """The screen's rule: below the penalty (0.5 ln N per parameter) screened; at or
    above it, or NaN (no fit to compare), held out."""
    pen = 2 * diag_mod.penalty_per_parameter(1000)
    assert pen == pytest.approx(math.log(1000))
    assert diag_mod.screened_by_fit(pen - 1e-9, pen) and diag_mod.screened_by_fit(-5.0, pen)
    assert not diag_mod.screened_by_fit(pen, pen) and not diag_mod.screened_by_fit(float("nan"), pen)
    assert diag_mod.penalty_per_parameter(0) == diag_mod.penalty_per_parameter(2)  # at least ln 2 / 2


def test_the_screen_compares_only_with_an_estimate_of_the_same_loss():
    """same_loss: an estimate fitted with the diagnosis' noise and weights (its reach
    included) is comparable; one fitted without the reach (tacest estimate's default),
    with other weights, or without a recorded configuration is not."""
    diag_cfg = EstimatorConfig().with_reach(diag_mod.DIAGNOSIS_REACH)

    def est(config):
        return Estimate(dim=2, shape="box", vertices=np.zeros((4, 2)), params={}, runs=[],
                        config=config.to_dict() if config is not None else {})

    assert diag_mod.same_loss(est(diag_cfg), diag_cfg)
    assert not diag_mod.same_loss(est(EstimatorConfig()), diag_cfg)
    assert not diag_mod.same_loss(est(diag_cfg.updated({"weights": {"contact": 2.0}})), diag_cfg)
    assert not diag_mod.same_loss(est(None), diag_cfg)


def test_a_transform_line_search_starts_the_estimator_once(recordings, stand_in, monkeypatch):
    """A data transform's line search fits the estimator's own start (cold) at its
    first value only; its later values start from the plain fit and from the search's
    best fit so far (TRANSFORM_COLD_ONCE).  Counted: the estimator's fits of the
    diagnosis, the plain model's one included."""
    run = _read(recordings["none"])
    cold = []
    fit = stand_in.fit_estimator
    monkeypatch.setattr(diag_mod, "fit_estimator", lambda *a, **k: cold.append(1) or fit(*a, **k))
    # an NLP candidate beside it: the warm back end, where transforms get cold starts
    opts = diag_mod.DiagnoseOptions(effects=("time_scale", "angular_damping"), fit_screen=False)
    d = diag_mod.diagnose([run], "box", options=opts)
    assert d.backend == "warm"
    ts = next(c for c in d.effects if c.name == "time_scale")
    assert len(ts.fits) == opts.fits_per_candidate == 3
    assert len(cold) == 1 + 1
    cold.clear()
    monkeypatch.setattr(diag_mod, "TRANSFORM_COLD_ONCE", False)
    diag_mod.diagnose([run], "box", options=opts)
    assert len(cold) == 1 + 3


def test_every_fit_of_a_diagnosis_has_its_reach(recordings, stand_in):
    """The diagnosis fits with DiagnoseOptions.reach (1 cm by default) whatever the
    configuration says, reports it in diagnosis.json, keeps the configuration's with
    None, and refuses a negative reach."""
    run = _read(recordings["none"])
    base = EstimatorConfig()
    assert base.noise.complementarity_reach == 0.0  # the estimator's default: off
    d = diag_mod.diagnose([run], "box", base, diag_mod.DiagnoseOptions(effects=("latency",)))
    assert stand_in.reaches == {diag_mod.DIAGNOSIS_REACH} and diag_mod.DIAGNOSIS_REACH > 0
    assert d.to_json()["options"]["reach"] == diag_mod.DIAGNOSIS_REACH
    stand_in.reaches.clear()
    own = base.with_reach(0.02)
    d = diag_mod.diagnose([run], "box", own, diag_mod.DiagnoseOptions(effects=("latency",), reach=None))
    assert stand_in.reaches == {0.02} and d.to_json()["options"]["reach"] == 0.02
    with pytest.raises(TacestError, match="reach must be a length >= 0"):
        diag_mod.diagnose([run], "box", options=diag_mod.DiagnoseOptions(reach=-0.01))


def test_a_plain_fit_that_fails_is_kept_at_its_budget(recordings, stand_in, monkeypatch):
    """When the plain model's fit to all data fails (with the reach, a bouncing box's
    plain fit ran out of IPOPT iterations: the plain model cannot bounce), the diagnosis
    goes on from its fit at the iteration budget instead of failing: that misfit is
    what the candidates are there to explain (measured on three bouncing boxes, e 0.6:
    restitution blamed, 100 % of the held-out gap closed)."""
    from tacest.errors import SolveFailedError

    calls = []

    def failing(*_a, **_k):
        calls.append(1)
        raise SolveFailedError("IPOPT failed in stage 'homotopy 2/2': Maximum_Iterations_Exceeded after 400 "
                               "iterations (no estimate written)")

    monkeypatch.setattr(diag_mod, "fit_estimator", failing)
    run = _read(recordings["latency"])
    # an NLP candidate (force_bias) makes the back end the warm one
    d = diag_mod.diagnose([run], "box", options=diag_mod.DiagnoseOptions(effects=("latency", "force_bias"),
                                                                        cold_starts=False))
    assert calls, "the plain fit did not go through fit_estimator"
    assert d.verdict == "latency", d.reason


def test_none_verdict_says_force_scale_cannot_be_excluded(recordings, stand_in, monkeypatch):
    """A sensor gain is the same data as a scaled mass: a "none" verdict with force_scale
    among the candidates says that it cannot be excluded (the stand-in's residuals do
    not change with the gain: the caveat holds all the same)."""
    run = _read(recordings["none"])
    d = diag_mod.diagnose([run], "box", options=diag_mod.DiagnoseOptions(effects=("latency", "force_scale")))
    assert d.verdict == "none", d.reason
    assert diag_mod.FORCE_SCALE_CAVEAT in d.reason
    # ... unless the object was weighed: then force_scale could have been blamed
    cfg = EstimatorConfig().updated({"prior": {"mass": 0.3, "mass_log_sigma": 0.02}})
    d = diag_mod.diagnose([run], "box", config=cfg,
                          options=diag_mod.DiagnoseOptions(effects=("latency", "force_scale")))
    assert d.verdict == "none", d.reason
    assert diag_mod.FORCE_SCALE_CAVEAT not in d.reason
    assert d.to_json()["mass_prior"] == {"mass": 0.3, "log_sigma": 0.02, "known": True}


def test_json_schema_and_report_folder(recordings, stand_in, tmp_path, monkeypatch):
    from click.testing import CliRunner

    # the stand-in's residuals do not change with force_bias: the latency decides

    from tacest.cli.diagnose import diagnose as cmd

    out = tmp_path / "report"
    res = CliRunner().invoke(cmd, [str(recordings["latency"]), "--effects", "latency,time_scale,force_bias",
                                   "-o", str(out), "--json", "--quiet"])
    assert res.exit_code == 0, res.output
    obj = json.loads(res.stdout)  # exactly one JSON object on stdout
    assert obj["verdict"] in ("none", "latency", "time_scale", "force_bias")
    assert isinstance(obj["effects"], list) and len(obj["effects"]) == 3
    for e in obj["effects"]:
        for key in ("name", "gap_before", "gap_after", "reduction", "params", "params_std", "status"):
            assert key in e, key
        assert isinstance(e["params"], dict) and isinstance(e["params_std"], dict)
    assert obj["verdict"] == "latency"  # the stand-in sees the 2-sample delay
    assert obj["effects"][0]["name"] == obj["verdict"]  # best first
    assert isinstance(obj["where"], list)
    for w in obj["where"]:
        assert set(("run", "start", "stop", "term", "share")) <= set(w)
        assert 0 <= w["share"] <= 1 and 0 <= w["start"] < w["stop"]
    files = {p.name for p in out.iterdir()}
    assert {"report.md", "heldout_gap.png", "residuals_run0.png", "diagnosis.json"} <= files
    assert "Verdict" in (out / "report.md").read_text()
    # a folder that is not a report is never replaced
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    res = CliRunner().invoke(cmd, [str(recordings["none"]), "--effects", "latency", "-o", str(other), "--quiet"])
    assert res.exit_code != 0 and (other / "keep.txt").exists()


# ------------------------------------------------------------------------------------
# failure paths through the installed CLI


def _tacest(*args):
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, timeout=120)


def _one_error_line(res):
    assert res.returncode == 2, (res.returncode, res.stderr)
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tacest: error:"), res.stderr
    return lines[0]


def test_missing_file_exits_2(tmp_path):
    line = _one_error_line(_tacest("diagnose", tmp_path / "nope.h5", "-o", tmp_path / "out"))
    assert "nope.h5" in line
    assert not (tmp_path / "out").exists()


def test_unknown_effect_exits_2(recordings, tmp_path):
    line = _one_error_line(_tacest("diagnose", recordings["none"], "--effects", "latency,wobble",
                                   "-o", tmp_path / "out"))
    assert "wobble" in line and "valid effects" in line
    with pytest.raises(TacestError):
        parse_effect_list("none")
    with pytest.raises(TacestError):
        candidate("none")


def test_negative_reach_exits_2(recordings, tmp_path):
    line = _one_error_line(_tacest("diagnose", recordings["none"], "--reach", "-0.01", "-o", tmp_path / "out"))
    assert "--reach" in line
    assert not (tmp_path / "out").exists()


def test_estimate_of_another_object_exits_2(recordings, tmp_path):
    run = _read(recordings["latency"])
    T = run.n_samples
    res = {t: np.zeros(T) for t in TERMS}
    est = Estimate(dim=2, shape="box", vertices=np.asarray(run.truth.vertices),
                   params={"mass": 0.5, "inertia": 1e-3, "friction_ground": 0.3, "friction_finger": 0.5},
                   runs=[RunEstimate(pose=np.zeros((T, 3)), velocity=np.zeros((T, 3)), residuals=res,
                                     source_file=str(recordings["latency"]),
                                     source_sha256=sha256_file(recordings["latency"]))],
                   solver_status="Solve_Succeeded", success=True)
    path = tmp_path / "est.h5"
    write_estimate(est, path)
    line = _one_error_line(_tacest("diagnose", recordings["none"], "--estimate", path, "-o", tmp_path / "out"))
    assert "other data" in line
    assert not (tmp_path / "out").exists()


def test_nothing_compared_is_undetermined_not_none(recordings, stand_in, monkeypatch):
    """When no held-out comparison could be made (every held-out fit of the plain model
    failed), the verdict is "undetermined", never "none" (no unmodelled effect)."""
    from tacest.errors import SolveFailedError

    def fails(*_a, **_k):
        raise SolveFailedError("IPOPT failed in stage 'homotopy 2/2': Restoration_Failed")

    monkeypatch.setattr(diag_mod._Context, "fold_objective", fails)
    run = _read(recordings["latency"])
    d = diag_mod.diagnose([run], "box", options=diag_mod.DiagnoseOptions(effects=("latency",)))
    assert d.verdict == diag_mod.UNDETERMINED == "undetermined"
    assert "no comparison possible" in d.reason
    assert d.to_json()["verdict"] == "undetermined"


def test_no_held_out_data_is_an_error_before_any_fit(recordings, stand_in):
    run = _read(recordings["none"])
    one_poke = run.replace(actions=None)
    with pytest.raises(TacestError, match="no held-out data"):
        diag_mod.diagnose([one_poke], "box", options=diag_mod.DiagnoseOptions(effects=("latency",)))
    assert stand_in.calls == 0


# ------------------------------------------------------------------------------------
# with the real estimator (slow)


@pytest.mark.slow
def test_latency_recovered_by_the_transform_path_with_the_estimator():
    """Fits of a 2-poke recording with a 2-sample tactile delay, its tactile streams
    advanced by k = 0..3: the delay the diagnosis keeps (the smallest k within
    LATENCY_TIE of the best fit) is within one sample of 2, and the plain minimum is 2
    or 3, as docs/diagnosis.md claims ("Latency's k"): a flag covers the interval
    (t-1, t], so a flag one sample too long or too short costs little once the model
    reads a touch's last flag as "touched somewhere in the interval" (measured: k = 0..3
    fit 17.2, 9.1, 8.5, 8.4; with the end's gap alone, which charged a fast release its
    open gap, 14.4 against 11.0 for k = 1 and 2).  No correction at all costs clearly
    more than one parameter's penalty."""
    from tacest.diagnosis.candidates import choose_transform_value
    from tacest.diagnosis.fitting import fit_local, weighted_objective
    from tacest.estimation.config import EstimatorConfig

    run = record_sim(SimOptions(seed=3, pokes=2, effects=["latency:samples=2"]))
    cfg = EstimatorConfig()
    base = fit_local([run], "box", cfg)
    objs = {0: weighted_objective(base.estimate, cfg)}
    for k in (1, 2, 3):
        f = fit_local([undo_latency(run, k)], "box", cfg, warm=base.estimate, warm_runs=list(base.estimate.runs))
        objs[k] = weighted_objective(f.estimate, cfg)
    assert abs(choose_transform_value("latency", objs) - 2) <= 1, objs
    assert min(objs, key=objs.get) in (2, 3), objs
    assert objs[0] - objs[2] > 3.0, objs  # the delay costs more than one parameter's penalty


def _falling_box(scale, T=80, dt=0.01, h=0.06, drop=0.4, sigma=1e-4, seed=0, t_release=0.05, length=1.0):
    """A box dropped from ``drop`` m above its resting height (plastic landing), seen
    only by pose observations (sigma m), written by a clock that runs at ``scale`` × the
    true rate (SPEC time_scale): /time and dt are scale × the true ones; and with its
    positions ``length`` × the true ones (a length scale error: a camera calibrated with
    the wrong target size; the angle and the noise as measured).  Before ``t_release``
    (s) it is held still in the air by a hand the model does not have."""
    from tacest.io.run import Run

    g = 9.81
    t = np.arange(T) * dt
    y = np.maximum(h / 2 + drop - 0.5 * g * np.maximum(t - t_release, 0.0) ** 2, h / 2)
    pose = np.stack([np.zeros(T), length * y, np.zeros(T)], 1)
    rng = np.random.default_rng(seed)
    obs = pose + rng.normal(size=pose.shape) * np.array([sigma, sigma, sigma / 0.05])
    return Run(dim=2, dt=scale * dt, time=scale * t, gravity=np.array([0.0, -g]), pose_obs=obs,
               sigma_position=sigma, sigma_angle=sigma / 0.05, prior={"size_bound": 0.3, "initial_pose": pose[0]})


@pytest.mark.parametrize("true_scale", [0.965, 1.035])
def test_time_scale_recovered_by_the_transform_path_where_gravity_shows_it(true_scale):
    """A clock error is absorbed by mass and friction wherever forces drive the motion,
    but not in free fall (gravity is fixed): on a falling box the line search of the
    diagnosis, with the real estimator, keeps the true scale (fits of 80 samples without
    fingers take well under a second), up to one grid step (1.5 %): the dynamics
    residual is whitened by sigma = process · g · dt, so a smaller dt whitens the same
    misfit more strongly and the objective leans toward 1 (a true 1.035 was fitted at
    1.02 in one of two trials).  Adding the normalizer Σ log sigma would remove that lean
    only if the configured process noise were the true one; it is far larger, and the
    normalizer then favours the largest scale on any recording.  The fits are the
    diagnosis' (DiagnoseOptions.fit_config: with the complementarity's reach), and the
    box is released at the first sample: a hand holding it first is a force the model
    does not have, which costs (with the reach) far more than the clock and drowns it.
    Measured: 149.2 at 1.0 against 122.9 at the true 0.965, 145.1 against 122.9 at
    1.035; without the reach 124.7 against 121.6 at 1.035 (the flying vertices' ground
    impulses fake most of the weaker gravity)."""
    from tacest.diagnosis.candidates import choose_transform_value, first_transform_values, next_transform_value
    from tacest.diagnosis.fitting import fit_local, weighted_objective
    from tacest.estimation.config import EstimatorConfig

    cfg = diag_mod.DiagnoseOptions().fit_config(EstimatorConfig())
    run = _falling_box(true_scale, t_release=0.0)
    base = fit_local([run], "box", cfg)
    objs = {1.0: weighted_objective(base.estimate, cfg)}
    queue = first_transform_values("time_scale")
    for _ in range(4):  # the diagnosis' budget is 3; one more to bracket either side
        s_try = queue.pop(0) if queue else next_transform_value("time_scale", objs)
        if s_try is None:
            break
        f = fit_local([undo_time_scale(run, s_try)], "box", cfg, warm=base.estimate,
                      warm_runs=list(base.estimate.runs))
        objs[s_try] = weighted_objective(f.estimate, cfg)
    chosen = choose_transform_value("time_scale", {k: v for k, v in objs.items() if k != 1.0})
    assert abs(chosen - true_scale) <= 0.0151, objs  # one grid step (1.5 %), with rounding
    assert objs[1.0] - objs[chosen] > 3.0, objs  # more than one parameter's penalty


@pytest.mark.parametrize("clock,length", [(0.92, 1.0), (1.08, 1.0), (1.0, 0.90), (1.0, 1.10)])
def test_clock_and_length_errors_to_ten_percent_are_found_by_the_time_scale_search(clock, length):
    """Clock errors of 8 % (outside the grid of the first versions, 2-5 %) and length
    errors of 10 % on a falling box seen by motion capture, with the real estimator and
    the diagnosis' own line search and budget (three fits to all data; fits of 80
    samples take under a second).  A length error L is the clock error s = 1/sqrt(L) to
    the model (candidates.TRANSFORM_GRIDS): every acceleration, gravity's included, is L
    times the true one.  Kept within 1.5 grid steps (2.25 %) of that scale, as the
    search does on a synthetic objective (test_time_scale_search_reaches_every_clock_
    error_of_the_grid; the objective leans toward 1 by about a percent,
    test_time_scale_recovered_by_the_transform_path_where_gravity_shows_it), and the
    error costs the plain model more than one parameter's penalty."""
    from tacest.diagnosis.candidates import TIME_SCALE_STEP
    from tacest.diagnosis.fitting import fit_local, weighted_objective

    cfg = diag_mod.DiagnoseOptions().fit_config(EstimatorConfig())
    run = _falling_box(clock, t_release=0.0, length=length)
    base = fit_local([run], "box", cfg)
    plain = weighted_objective(base.estimate, cfg)

    def objective(s_try):
        if s_try == 1.0:
            return plain
        f = fit_local([undo_time_scale(run, s_try)], "box", cfg, warm=base.estimate,
                      warm_runs=list(base.estimate.runs))
        return weighted_objective(f.estimate, cfg)

    objs = {}
    fitted, kept = _walk("time_scale", lambda v: objs.setdefault(v, objective(v)), budget=diag_mod.FITS_PER_CANDIDATE)
    expected = clock / math.sqrt(length)
    assert abs(kept - expected) <= 1.5 * TIME_SCALE_STEP + 1e-9, (expected, objs)
    assert plain - objs[kept] > 3.0, objs


def test_the_reach_term_is_free_on_the_ground_and_the_height_beyond_it_above():
    """problem.reach_excess(phi, r) = smoothed max(phi - r, 0) / r at r = 1 cm.  On the
    ground it must be negligible against the saturated psi = 1 (below 1e-5; the
    exponential tail gives 5e-6): a load-carrying vertex pays lambda_n times it, so an
    algebraic tail (eps²/4r = 0.25 %) priced the weight and biased the mass.  5 mm
    beyond the reach it is 0.5 reaches to within 1 % (the 1 mm smoothing's tail there is
    e^-5 mm/1 mm = 0.7 % of a mm); it never decreases with the height."""
    import casadi as ca

    from tacest.dynamics.laws import reach_excess

    phi = ca.SX.sym("phi")
    f = ca.Function("f", [phi], [reach_excess(phi, 0.01)])
    assert 0.0 <= float(f(0.0)) < 1e-5
    assert abs(float(f(0.015)) - 0.5) < 0.01 * 0.5
    heights = np.linspace(-0.005, 0.05, 200)
    values = np.array([float(f(h)) for h in heights])
    assert np.all(np.diff(values) >= 0)


@pytest.mark.parametrize("reach", [0.0, 0.01])
def test_complementarity_reach_stops_ground_impulses_at_a_distance(reach):
    """A falling box written by a clock 5 % fast (gravity looks 10 % weaker): the
    saturating complementarity alone lets the fit hold the box up with ground impulses
    at vertices far above the ground (measured: up to 20 % of the weight per sample,
    0.27 N·s over the flight); with noise.complementarity_reach = 1 cm an impulse there
    also costs its height in reaches, and the flight's ground impulses vanish (measured:
    0.3 % of the weight per sample at most), which is what leaves the clock error to
    the time_scale candidate.  Thresholds: 5 % and 1 % of the weight per sample, well
    apart from both measurements; a sample counts as flying when the box's centre is
    3 cm above its lowest, i.e. its lowest vertex 3 cm up."""
    from tacest.dims import estimate_runs

    run = _falling_box(1.05)
    est = estimate_runs([run], "box", EstimatorConfig().with_reach(reach))
    r = est.runs[0]
    flying = r.pose[:, 1] > r.pose[:, 1].min() + 0.03
    assert flying.sum() > 20  # the drop's flight, ~0.28 s
    weight_per_sample = est.params["mass"] * 9.81 * run.dt  # N·s
    largest = np.abs(np.asarray(r.impulses["ground_normal"])[flying]).max() / weight_per_sample
    if reach:
        assert largest < 0.01, largest
    else:
        assert largest > 0.05, largest  # what the reach removes: the test can fail


def _bouncing_box(e, T=100, dt=0.01, h=0.06, drop=0.1, sigma=1e-4, seed=0, t_release=0.05):
    """A box of height h dropped from ``drop`` m above its resting height at t_release s,
    bouncing with coefficient of restitution e (no rotation; bounces slower than 2 cm/s
    end), seen only by pose observations (sigma m).  Integrated at dt/1000 and sampled
    at dt."""
    from tacest.io.run import Run

    g, sub = 9.81, 1000
    y, v = h / 2 + drop, 0.0
    ys = np.empty(T * sub)
    for i in range(T * sub):
        ys[i] = y
        if i * dt / sub < t_release:
            continue
        v -= g * dt / sub
        y += v * dt / sub
        if y < h / 2:
            y, v = h / 2, (-e * v if -e * v > 0.02 else 0.0)
    t = np.arange(T) * dt
    pose = np.stack([np.zeros(T), ys[::sub], np.zeros(T)], 1)
    obs = pose + np.random.default_rng(seed).normal(size=pose.shape) * np.array([sigma, sigma, sigma / 0.05])
    return Run(dim=2, dt=dt, time=t, gravity=np.array([0.0, -g]), pose_obs=obs, sigma_position=sigma,
               sigma_angle=sigma / 0.05, prior={"size_bound": 0.3, "initial_pose": pose[0]})


@pytest.mark.parametrize("true_e", [0.3, 0.6])
def test_restitution_augmentation_recovers_e_from_an_observed_bounce(true_e):
    """Where the bounces are in the data (a dropped box seen by motion capture, landing
    at 1.2 m/s), the restitution augmentation gives e back and explains most of what the
    plastic model cannot (fits of 100 samples: about a second each)."""
    from tacest.dims import estimate_runs

    run = _bouncing_box(true_e)
    plain = estimate_runs([run], "box")
    est = estimate_runs([run], "box", effects=("restitution",))
    e = est.params["restitution.e"]
    # 30 %: the impact law is discrete, its approach and rebound speeds are averages over
    # the sample intervals around an impact that happens inside one; measured e = 0.24,
    # 0.41, 0.54 for 0.3, 0.5, 0.7 (-19 to -23 %)
    assert abs(e - true_e) <= 0.3 * true_e, (e, true_e)
    # the misfit itself, without the Occam term (a price of the trajectory's freedom
    # that both fits pay, about the same: it is no misfit to explain)
    fit, fit_plain = (x.objective - occam_objective(x, EstimatorConfig()) for x in (est, plain))
    assert fit < 0.6 * fit_plain, (fit, fit_plain)


NLP_EFFECTS = {  # effect: (record spec, parameter(s), relative tolerance)
    # strength of the effect relative to its noise: the bias is seen on every sample
    # without contact (σ_force 0.02 N vs 0.2-0.3 N), the compliance on every resting
    # sample (3000 N/m sinks a 0.2-1 kg box by 0.7-3 mm vs σ_pen 0.5 mm): 30 % each.
    # Two parameters are checked as a vector: error norm within the tolerance × the
    # norm of the truth (a small component cannot hide a large error in the other)
    "force_bias": ("force_bias:fx=0.3,fy=-0.2", ("fx", "fy"), 0.3),
    "soft_contact": ("soft_contact:stiffness=3000", "stiffness", 0.3),
    # drag and damping are a few percent of friction on quasi-static pokes (docs/
    # diagnosis.md): recovered within 50 %, or left unresolved by the information
    # (std above 50 % of the truth) with the truth within 3 std of the estimate
    "angular_damping": ("angular_damping", "c", 0.5),
    "linear_drag": ("linear_drag", "b", 0.5),
    "restitution": ("restitution:e=0.6", "e", 0.3),
    "force_scale": ("force_scale:gain=1.3", "gain", 0.1),
    "com_offset": ("com_offset", ("dx", "dy"), 0.5),
}
#: augmentations whose parameter a 6-poke box recording (seed 4) does not give back,
#: with what was measured (docs/diagnosis.md "NLP augmentations", "Benchmark").  Each is
#: a limit of this recording (the parameter is not in its data), not of the code: the
#: test each reason names recovers it from data that show it.  Listed as expected
#: failures without being run (they cost two minutes of the suite and cannot pass on
#: this recording)
NLP_NOT_RECOVERED = {
    "force_scale": "not identifiable in principle: every model force scales with the mass, every measured "
                   "force with the gain, so only gain x mass is determined (the split is the priors'); with a "
                   "weighed mass it is (test_force_scale_gain_is_recovered_with_a_weighed_mass)",
    "restitution": "the bounces are not in the data: the box tips 5-7 deg and lands at up to 0.49 m/s, but "
                   "after the finger has left (tactile data only); the plain fit's objective (56.9) equals "
                   "the clean recording's (57.0) and the augmented fit ends at e = 0.15 (truth 0.6) in a "
                   "worse minimum (59.5, mass 7 g for 0.23 kg); where a bounce is observed the "
                   "augmentation recovers e (test_restitution_augmentation_recovers_e_from_an_observed_bounce)",
    "com_offset": "dx 0.009 m for 0.015 m but dy 0.036 m for 0.003 m, objective 56.5 -> 53.5 (less than two "
                  "parameters' penalty): the COM is seen only while the box tilts (<= 7 deg here); from "
                  "tosses it is (test_free_motion_augmentations_are_recovered_from_tosses)",
}


@pytest.mark.slow
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.xfail(reason=NLP_NOT_RECOVERED[n], run=False))
                                  if n in NLP_NOT_RECOVERED else n for n in sorted(NLP_EFFECTS)])
def test_nlp_augmentation_recovers_its_parameter(name):
    from tacest.dims import estimate_runs
    from tacest.sim.effects import effects_from_json

    spec, params, rel = NLP_EFFECTS[name]
    params = (params,) if isinstance(params, str) else params
    run = record_sim(SimOptions(seed=4, pokes=6, effects=[spec]))
    truth = np.array([effects_from_json(run.truth.effects)[0].params[p] for p in params])
    est = estimate_runs([run], "box", effects=(name,))
    assert est.model == [name]
    keys = [next((k for k in est.params if k == f"{name}.{p}"), None) for p in params]
    assert None not in keys, est.params
    value = np.array([est.params[k] for k in keys])
    if np.linalg.norm(value - truth) <= rel * np.linalg.norm(truth):
        return
    # not recovered: acceptable only for drag and damping, where the information says
    # the data do not resolve the parameter and the truth is within 3 std
    std = est.std.get(keys[0], float("nan"))
    assert name in ("linear_drag", "angular_damping"), (value, truth, std)
    assert std > rel * abs(truth[0]) and abs(value[0] - truth[0]) <= 3 * std, (value, truth, std)


def _tip_aim(i, state):
    """Poke i of a tipping sequence (POKE_NAMES vector) at the object of a WorldState:
    35 % of the box's height above its centroid, from alternate sides, 5 deg above the
    horizontal, 4 cm past the first touch at 0.2 m/s: the box tips and lands, as the
    diagnosis benchmark's pokes."""
    from tacest.sim.pokes import CLEARANCE

    world = state.world()
    c, verts = world.centroid__world(), world.vertices__world()
    target = c + np.array([0.0, 0.35 * float(np.ptp(verts[:, 1]))])
    angle = math.radians(5.0) if i % 2 == 0 else math.pi - math.radians(5.0)
    depth = 0.04
    return np.array([0.0, angle, target[0], target[1], depth, (CLEARANCE + depth) / 0.2])


def _tipping_pokes(opts, n=3):
    """A recording of n fast pokes (_tip_aim) from alternate sides: the box tips and lands."""
    from tacest.sim.record import initial_state, simulate_aimed_pokes

    return simulate_aimed_pokes(_tip_aim, n, opts, state=initial_state(opts))


def _tosses(opts, n=2):
    """n runs of one object, each a toss (released over x = 0 at a random height, speed
    and spin, seen flying, landing and coming to rest: tacest.sim.record.toss_state)
    followed by one tipping poke (_tip_aim), as the diagnosis benchmark's toss design."""
    from tacest.sim.record import initial_state, simulate_aimed_pokes, simulate_pokes, state_from_run, toss_state

    rng = np.random.default_rng([opts.seed, 99])
    state = initial_state(opts)
    runs = []
    for i in range(n):
        toss = simulate_pokes(toss_state(state, rng, x=0.0), np.zeros((0, 6)), opts, noise_key=100 + i,
                              settle_first=True)
        run = simulate_aimed_pokes(lambda j, st: _tip_aim(i, st), 1, opts, run=toss)
        runs.append(run)
        state = state_from_run(run)
    return runs


#: effect: (record spec, parameter(s), relative tolerance) on tosses, where the object
#: moves freely: what friction and inertia absorbed on pokes (NLP_EFFECTS, NLP_NOT_RECOVERED)
TOSS_EFFECTS = {
    # drag and damping act alone in flight: 25 % (measured here c 0.0149 for 0.0167 and
    # b 3.32 for 3.55, 6-11 % off; the diagnosis benchmark's toss design fitted 0.0183
    # and 3.10: a 10 ms implicit step of an exponential decay, and the landings)
    "angular_damping": ("angular_damping", "c", 0.25),
    "linear_drag": ("linear_drag", "b", 0.25),
    # the body turns about its COM in flight: the offset as a vector within 20 %
    # (measured (21.4, -12.7) mm for (21.2, -12.5), 0.9 %)
    "com_offset": ("com_offset", ("dx", "dy"), 0.2),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(TOSS_EFFECTS))
def test_free_motion_augmentations_are_recovered_from_tosses(name):
    """Two tosses of a box seen by motion capture (0.5 mm), each followed by a tipping
    poke; the effect drawn at random in its range (docs/effects.md); mass unknown."""
    from tacest.dims import estimate_runs
    from tacest.sim.effects import effects_from_json

    spec, params, rel = TOSS_EFFECTS[name]
    params = (params,) if isinstance(params, str) else params
    runs = _tosses(SimOptions(object_spec="box", seed=0, pokes=0, observe_pose=5e-4, effects=[spec]))
    truth = np.array([effects_from_json(runs[0].truth.effects)[0].params[p] for p in params])
    est = estimate_runs(runs, "box", effects=(name,))
    value = np.array([est.params[f"{name}.{p}"] for p in params])
    assert np.linalg.norm(value - truth) <= rel * np.linalg.norm(truth), (value, truth)
    assert all(est.identifiable[f"{name}.{p}"] for p in params), est.identifiable


@pytest.mark.slow
def test_force_scale_gain_is_recovered_with_a_weighed_mass():
    """force_scale is a scaled mass unless the mass is known (NLP_NOT_RECOVERED): with the
    object weighed (mass prior at the truth, log sigma 0.02) and pokes that tip the box
    (fast, 35 % of its height above the centroid, pose observed at 0.5 mm, as the
    diagnosis benchmark's design), the gain comes back within 10 % and the mass stays at
    the scale's reading.  (On the sliding pushes of the recording above a gain still
    trades with the ground friction, mu·m·g, even with the mass known: 0.68 for 1.3.)"""
    from tacest.dims import estimate_runs

    run = _tipping_pokes(SimOptions(object_spec="box", seed=0, pokes=0, observe_pose=5e-4,
                                    effects=["force_scale:gain=1.3"]))
    cfg = EstimatorConfig().updated({"prior": {"mass": float(run.truth.mass), "mass_log_sigma": 0.02}})
    est = estimate_runs([run], "box", config=cfg, effects=("force_scale",))
    # 10 %: the tolerance of the other single-parameter sensor effect checks above
    assert abs(est.params["force_scale.gain"] - 1.3) <= 0.1 * 1.3, est.params
    # 3 sigma of the prior: the data did not pull the mass off the scale's reading
    assert abs(np.log(est.params["mass"] / run.truth.mass)) <= 3 * 0.02, est.params
    # the reported uncertainty is the posterior's: the weighing error (2 %) carries over
    # to the gain, which the data alone know only as gain x mass (their pseudo-inverse
    # gave 0.005 here); 0.8: along gain x mass the data add nothing to the prior's
    # information, so the posterior std stays near the weighing error's share
    assert est.std["force_scale.gain"] >= 0.8 * 0.02 * est.params["force_scale.gain"], est.std
    assert est.std["mass"] >= 0.8 * 0.02 * est.params["mass"], est.std
    assert abs(est.params["force_scale.gain"] - 1.3) <= 3 * est.std["force_scale.gain"], (est.params, est.std)


@pytest.mark.slow
def test_soft_contact_stiffness_is_recovered_from_tipping_pokes():
    """soft_contact on pokes that tip the box (pose observed at 0.5 mm), mass unknown:
    the ground's stiffness and the box's mass come back, and the damper's time constant
    to within its known bias.  Truth 2000 N/m and 60 N·s/m (c/k 30 ms, 0.7 × critical
    for this box), mass 0.821 kg.  Measured with the plate as a state of every sample:
    1920 N/m, 0.799 kg, c/k 21 ms.  (With a plate that had no memory between samples:
    2176 N/m, mass 0.66-0.71 kg, c/k 27-68 ms; docs/diagnosis.md, NLP augmentations,
    soft_contact.)"""
    from tacest.dims import estimate_runs

    k, c = 2000.0, 60.0
    run = _tipping_pokes(SimOptions(object_spec="box", seed=0, pokes=0, observe_pose=5e-4,
                                    effects=[f"soft_contact:stiffness={k},damping={c}"]))
    est = estimate_runs([run], "box", effects=("soft_contact",))
    # 30 %: as the sliding recording's stiffness check above (NLP_EFFECTS)
    assert abs(est.params["soft_contact.stiffness"] - k) <= 0.3 * k, est.params
    assert est.identifiable["soft_contact.compliance"]
    # 10 %: the mass of a clean recording of this design comes back within a few percent
    # (test_force_scale_gain_is_recovered_with_a_weighed_mass holds it at 2 % by a prior)
    assert abs(est.params["mass"] - run.truth.mass) <= 0.1 * run.truth.mass, est.params
    # the time constant within a factor 2: the fitted plate is massless and its load is
    # held constant over each 10 ms sample, the simulated one is a 30 g body integrated
    # at 0.5 ms (measured 0.7 × the truth here, 0.8 × on the sliding recording above)
    assert 0.5 * c / k <= est.params["soft_contact.tau"] <= 2 * c / k, est.params


def _down_face(vertices, angle):
    """Index of the face (vertex i to i+1, CCW) whose outward normal points most down."""
    V = np.asarray(vertices, float)
    e = np.roll(V, -1, axis=0) - V
    n = np.stack([e[:, 1], -e[:, 0]], 1) / np.linalg.norm(e, axis=1, keepdims=True)
    ny = n[:, 0] * np.sin(angle) + n[:, 1] * np.cos(angle)  # world y of the rotated normals
    return int(np.argmin(ny))


def _face_friction_recording():
    """Three random pokes (tactile only) of the box of seed 4 (0.23 kg), its faces' ground
    friction 0.377, 0.141, 0.322, 0.159 (drawn); it slides on face 0 only."""
    return record_sim(SimOptions(seed=4, pokes=3, effects=["face_friction"]))


def test_face_friction_augmentation_recovers_the_face_on_the_ground():
    """face_friction on a poked box, the object weighed (mass prior at the scale's
    reading, log sigma 0.02): the coefficient of the face the box slides on (the face
    facing the ground at the start, in the truth and in the estimate) is recovered
    within 15 %.  In steady sliding only mu (m g + push) is observed, so the face's
    coefficient is as good as the mass: weighed, it is right (measured 0.386 for 0.377;
    0.378 from six pokes); unweighed, see the next test.  Faces that never touched the
    ground keep their prior value (the ground friction).  ~6 s."""
    from tacest.dims import estimate_runs
    from tacest.sim.effects import effects_from_json

    run = _face_friction_recording()
    values = effects_from_json(run.truth.effects)[0].params["values"]
    truth = values[_down_face(run.truth.vertices, run.truth.pose[0, 2])]
    cfg = EstimatorConfig().updated({"prior": {"mass": float(run.truth.mass), "mass_log_sigma": 0.02}})
    est = estimate_runs([run], "box", config=cfg, effects=("face_friction",))
    k = _down_face(est.vertices, est.runs[0].pose[0, 2])
    got = est.params["face_friction.values"][k]
    # 15 %: the tolerance of the toss test below and of the ground friction in
    # docs/estimation.md's benchmark
    assert abs(got - truth) <= 0.15 * truth, (got, truth, est.params["face_friction.values"], values)
    others = [v for j, v in enumerate(est.params["face_friction.values"]) if j != k]
    assert np.allclose(others, est.params["friction_ground"], rtol=0.02), est.params


def test_face_friction_unweighed_no_longer_collapses_to_a_light_object():
    """The regression that a non-strict expected failure once hid, and then a strict test
    held as a known limitation: without a weighed mass the plain fit of this recording
    fell into the light-object collapse (0.004 kg for 0.23, ground friction 2.0 at its
    bound; face_friction 0.015 kg with 3.50 for the face's 0.377).  Slow sliding pushes
    tell mu (m g + push) only, so a start in the light basin stays there; the sampling
    start with two runs and the goodness-of-fit restarts (docs/estimation.md, "Dynamic
    pokes") begin in the right one.  Measured: plain 0.2330 kg for 0.2308 (+0.9 %),
    face 0.384 for 0.377 (+1.9 %).  The tolerances are the weighed test's (15 % on the
    face, the ground friction's in docs/estimation.md's benchmark) and 10 % on the mass
    (the soft-contact test's); a return of the collapse (a tenth of the mass) fails
    both.  ~10 s."""
    from tacest.dims import estimate_runs
    from tacest.sim.effects import effects_from_json

    run = _face_friction_recording()
    values = effects_from_json(run.truth.effects)[0].params["values"]
    truth = values[_down_face(run.truth.vertices, run.truth.pose[0, 2])]
    plain = estimate_runs([run], "box")
    est = estimate_runs([run], "box", effects=("face_friction",))
    got = est.params["face_friction.values"][_down_face(est.vertices, est.runs[0].pose[0, 2])]
    for fit in (plain, est):
        assert abs(fit.params["mass"] - run.truth.mass) <= 0.1 * run.truth.mass, fit.params
    assert abs(got - truth) <= 0.15 * truth, (got, truth, est.params["face_friction.values"])


@pytest.mark.slow
def test_restitution_is_recovered_from_tumbling_landings():
    """restitution on three tosses of a weighed box (each followed by a tipping poke;
    e 0.42): spinning corner landings at 1.5-2.7 m/s, whose impacts fall anywhere inside
    a 10 ms interval.  e within 30 % (measured 0.39, -5 %), and the plastic model's
    misfit reduced by a third at least (measured 7302 -> 4719: this cold fit ends in a
    local minimum with the mass at half the scale's reading; the diagnosis' fits of the
    benchmark's six-run recording reach 1783 from 7831 with the mass and e right,
    docs/diagnosis.md).  Until the law followed impacts inside an interval (an impact
    memory, the impulses at the impact's levers) such fits ended at e 0.75."""
    from tacest.dims import estimate_runs
    from tacest.sim.effects import effects_from_json

    # e as it was drawn for seed 0 when the draw was U(0.4, 0.8) (the measurements below)
    runs = _tosses(SimOptions(object_spec="box", seed=0, pokes=0, observe_pose=5e-4,
                              effects=["restitution:e=0.41554442483900644"]), n=3)
    truth = effects_from_json(runs[0].truth.effects)[0].params["e"]
    # weighed: unweighed, the fit settles on a light object (0.41 kg for 0.82, e 0.52)
    cfg = EstimatorConfig().updated({"prior": {"mass": float(runs[0].truth.mass), "mass_log_sigma": 0.02}})
    plain = estimate_runs(runs, "box", config=cfg)
    est = estimate_runs(runs, "box", config=cfg, effects=("restitution",))
    assert abs(est.params["restitution.e"] - truth) <= 0.3 * truth, est.params
    # 0.7: the plastic model leaves the bounces unexplained; the law explains a good part
    assert est.objective < 0.7 * plain.objective, (est.objective, plain.objective)


@pytest.mark.slow
def test_face_friction_is_recovered_on_the_faces_tosses_and_pokes_slide_on():
    """face_friction on three tosses, each followed by a tipping poke (seed 0, faces
    1.02, 0.36, 1.19, 0.43): the box lands and tumbles on several faces and the pokes
    slide it on the slippery ones.  The faces it ends the pokes on (it slid there) come
    back within 15 % (the random-poke test's tolerance; measured 5 % and 11 %); every
    face is within 3 std of the information's uncertainty of its offset from the ground
    friction (face_friction.d<k>; the ground friction itself is known far better: a face the box only
    sticks or pivots on bounds its coefficient from below: measured 1.22 ± 0.40 and
    0.95 ± 0.26 for the two grippy faces)."""
    from tacest.dims import estimate_runs
    from tacest.sim.effects import effects_from_json

    runs = _tosses(SimOptions(object_spec="box", seed=0, pokes=0, observe_pose=5e-4, effects=["face_friction"]), n=3)
    values = np.array(effects_from_json(runs[0].truth.effects)[0].params["values"])
    est = estimate_runs(runs, "box", effects=("face_friction",))
    got = np.array(est.params["face_friction.values"])
    slid = {_down_face(est.vertices, er.pose[-1, 2]) for er in est.runs}
    # the estimate's face k is the truth's face k (same corner order from the same
    # start angle), checked on the truth's faces down at the same samples
    assert slid == {_down_face(r.truth.vertices, r.truth.pose[-1, 2]) for r in runs}
    for k in slid:
        assert abs(got[k] - values[k]) <= 0.15 * values[k], (k, got, values)
    std = np.array([est.std[f"face_friction.d{k}"] for k in range(len(values))])
    assert np.all(np.abs(got - values) <= 3 * std), (got, values, std)


def test_restitution_leaves_slow_landings_to_the_plain_model():
    """A box lowered onto the table (landing at 0.04 m/s, below problem.BOUNCE_SPEED)
    and seen by motion capture at 0.5 mm: no bounce the data could tell, so the
    restitution model (whatever e it picks) fits as the plain one does.  With the
    previous gate a/(a + 0.02 m/s) its impact law weighed every slow approach and the
    objective rose by 19.6."""
    from tacest.dims import estimate_runs

    run = _bouncing_box(0.0, T=150, drop=1e-4, sigma=5e-4)
    plain = estimate_runs([run], "box")
    est = estimate_runs([run], "box", effects=("restitution",))
    # 1.0: a third of one parameter's penalty (0.5 ln 150 = 2.5)
    assert abs(est.objective - plain.objective) < 1.0, (plain.objective, est.objective, est.params["restitution.e"])

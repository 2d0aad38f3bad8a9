"""The goodness-of-fit test every estimate carries (tacest.estimation.fitquality).

It must (1) stay quiet on residuals that are noise at the configured levels, at no more
than its stated false-alarm rate, (2) flag and locate a misfit, (3) count degrees of
freedom where the estimators put residuals (2-D and 3-D), and (4) mark a fit in a wrong
basin, written to and read back from the estimate file.
"""

from __future__ import annotations

import numpy as np
import pytest

from tacest.estimation.fitquality import goodness_of_fit
from tacest.estimation.floor import TERMS, residual_dof
from tests.test_estimator import pushed_box_run
from tests.test_estimator3d import tosses  # noqa: F401  (the fixture)


def _noise_residuals(run, K, rng, inflate=None):
    """Per-sample 0.5·‖r‖² of whitened Gaussian noise at the configured level (a
    chi-square draw of each sample's degrees of freedom), optionally times ``inflate``
    = (term, start, stop, factor) on one stretch."""
    dof = residual_dof(run, K)
    res = {t: 0.5 * rng.chisquare(np.maximum(d, 1e-9)) * (d > 0) for t, d in dof.items()}
    if inflate:
        term, a, b, f = inflate
        res[term][a:b] *= f
    return res


def test_noise_at_the_configured_level_is_rarely_flagged():
    """200 draws of pure noise: the test's family-wise false-alarm rate is at most ALPHA
    (1 %); flagging more than 8 of 200 has probability < 1e-3 at that rate (binomial),
    so a failure here means the test is miscalibrated, not unlucky."""
    run = pushed_box_run(T=120, k0=30)
    rng = np.random.default_rng(0)
    alarms = sum(not goodness_of_fit([_noise_residuals(run, 4, rng)], [run], 4).consistent for _ in range(200))
    assert alarms <= 8, alarms


def test_a_misfit_stretch_is_flagged_where_it_is():
    """Contact residuals ten times the noise on samples 40-55 (the contact phase): the
    fit is inconsistent, its worst window lies there, and its std scale exceeds 1."""
    run = pushed_box_run(T=120, k0=30)
    rng = np.random.default_rng(1)
    q = goodness_of_fit([_noise_residuals(run, 4, rng, ("contact", 40, 55, 10.0))], [run], 4)
    assert not q.consistent
    w = q.worst[0]
    assert w["term"] == "contact" and w["start"] < 55 and w["stop"] > 40
    assert q.std_scale > 1.5
    assert "NOT consistent" in q.summary() and "contact" in q.summary()


def test_a_local_misfit_is_consistent_said_and_its_std_widened():
    """Dissipation residuals 40 times the noise on 4 samples of 400 (a fingertip sliding
    off a corner at speed, the model's simplification at an instant): flagged, but local
    (1 % of the samples, LOCAL_FRACTION 5 %), so consistent, with the window kept, the
    std scale above 1 and the summary saying so.  The same factor on 40 samples (10 %)
    is no local misfit: not consistent."""
    from tacest.estimation.fitquality import LOCAL_FRACTION, quality_summary

    run = pushed_box_run(T=400, k0=30)
    rng = np.random.default_rng(2)
    short = goodness_of_fit([_noise_residuals(run, 4, rng, ("dissipation", 200, 204, 40.0))], [run], 4)
    assert short.consistent and short.local_misfit and short.local, short
    assert short.worst and short.worst[0]["term"] == "dissipation" and not short.terms
    assert short.flagged_samples <= LOCAL_FRACTION * short.n_samples and short.std_scale > 1.5
    said = quality_summary(short.to_json())
    assert said.startswith("consistent with the noise floor but for a local misfit") and "dissipation in run 0" in said
    assert f"x{short.std_scale:.2f}" in said
    long = goodness_of_fit([_noise_residuals(run, 4, rng, ("dissipation", 200, 240, 40.0))], [run], 4)
    assert not long.consistent and not long.local_misfit and "NOT consistent" in long.summary()
    quiet = goodness_of_fit([_noise_residuals(run, 4, np.random.default_rng(3))], [run], 4)
    assert quiet.consistent and not quiet.local_misfit and quiet.std_scale == 1.0


def test_a_fit_at_implausible_friction_is_marked_restarted_and_said_so(tmp_path):
    """The pushed box (ground friction 0.4) fits at about 0.4.  With a plausible range
    that excludes it ([prior] friction_plausible = [0.9, 1.5], as if 0.4 were the
    signature of a wrong basin) the fit is marked NOT consistent with the friction
    named, every start is judged not right (misfit_local false, its ``implausible``
    listed, so the restarts are tried), and the mark survives the estimate file; with
    the default range the same fit is consistent and nothing is listed.  A range that
    is no range is refused."""
    from tacest.dims import estimate_runs
    from tacest.errors import TacestError
    from tacest.estimation.config import load_config
    from tacest.estimation.fitquality import quality_summary
    from tacest.estimation.result import implausible_friction
    from tacest.estimation.solver import _restart_reason
    from tacest.io.estimate import read_estimate, write_estimate

    run = pushed_box_run()
    plain = estimate_runs([run], "box")
    assert plain.consistent is True and "implausible" not in plain.fit_quality
    assert 0.3 < plain.params["friction_ground"] < 0.5
    narrow = load_config(None, overrides={"prior": {"friction_plausible": [0.9, 1.5]}})
    odd = estimate_runs([run], "box", config=narrow)
    assert odd.consistent is False
    assert any(x.startswith("friction_ground") and x.endswith("< 0.9") for x in odd.fit_quality["implausible"])
    said = quality_summary(odd.fit_quality)
    assert said.startswith("NOT a plausible fit") and "friction_ground" in said
    starts = [a for a in __import__("json").loads(odd.extra_attrs["starts"]) if "objective" in a]
    assert starts and all(a["misfit_local"] is False and a["implausible"] for a in starts)
    assert "implausible friction" in _restart_reason(starts[0], 0.1)
    write_estimate(odd, tmp_path / "odd.h5")
    assert read_estimate(tmp_path / "odd.h5").fit_quality["implausible"] == odd.fit_quality["implausible"]
    assert implausible_friction({"friction_ground": 2.0, "friction_finger": 0.5}, {}) == ["friction_ground 2 > 1.8"]
    assert implausible_friction({"friction_ground": 0.5, "friction_finger": 0.01}, {}) == ["friction_finger 0.01 < 0.02"]
    for bad in ([0.5, 0.5], [1.0], [-0.1, 1.0], "0.02, 1.8"):
        with pytest.raises(TacestError, match="friction_plausible"):
            load_config(None, overrides={"prior": {"friction_plausible": bad}})


def _assert_residuals_live_where_dof_says(est, runs):
    """Every residual the estimator stores at a sample is zero where residual_dof gives
    that sample no degrees of freedom, and terms with degrees of freedom somewhere have
    residuals somewhere (the counts and the estimator agree on where terms live)."""
    K = len(est.vertices)
    for r_est, run in zip(est.runs, runs):
        dof = residual_dof(run, K)
        for term in TERMS:
            if term not in r_est.residuals:
                continue
            res = np.asarray(r_est.residuals[term])
            assert np.all(res[dof[term] == 0] <= 1e-12), (term, np.nonzero((dof[term] == 0) & (res > 1e-12)))


@pytest.mark.slow
def test_2d_fit_is_consistent_and_a_wrong_shape_is_not(tmp_path):
    """A 2-D known-answer fit (seed 1, six pokes) is consistent; the same data with the
    box held at 80 % of its fitted extents (a wrong basin made on purpose) are not, and
    the mark survives the estimate file."""
    from tacest.estimation.estimator import ImplicitEstimator, theta_of, warm_start
    from tacest.dims import estimate_runs
    from tacest.io.estimate import read_estimate, write_estimate
    from tacest.sim.record import SimOptions, record_sim

    run = record_sim(SimOptions(object_spec="box", seed=1, pokes=6))
    good = estimate_runs([run], "box")
    assert good.consistent is True, good.fit_quality
    _assert_residuals_live_where_dof_says(good, [run])

    free = ImplicitEstimator([run], "box")
    th = theta_of(free, good)
    th[: free.problem.n_shape] *= 0.8
    held = ImplicitEstimator([run], "box", pinned_theta=th, pin="shape")
    wrong = held.result(held.solve_from(warm_start(held, good)), 0.0)
    assert wrong.consistent is False
    write_estimate(wrong, tmp_path / "wrong.h5")
    back = read_estimate(tmp_path / "wrong.h5")
    assert back.consistent is False and back.fit_quality["worst"]
    # the widened error bars: every std of the inconsistent fit is scaled by std_scale
    scale = back.fit_quality["std_scale"]
    assert scale > 1.0


def test_3d_fit_residuals_live_where_dof_says(tosses):
    """3-D: two short noiseless tosses (the project's own model): the fit is consistent
    and its residuals sit where residual_dof counts degrees of freedom (the stage terms
    start at sample 2, the rest term at sample 1)."""
    from tacest.estimation.estimator3d import estimate_3d

    est = estimate_3d(tosses, "box")
    assert est.consistent is True, est.fit_quality
    _assert_residuals_live_where_dof_says(est, tosses)


def test_the_chi_square_functions_are_scipy_stats_own():
    """floor.chi2_pvalue and chi2_median (scipy.special's chdtrc / chdtri, which spare
    every estimate scipy.stats' import) give scipy.stats.chi2's sf and median, to 1e-12
    relative (both evaluate the same incomplete gamma function), with phi widening the
    degrees of freedom as documented."""
    from scipy.stats import chi2

    from tacest.estimation.floor import chi2_median, chi2_pvalue

    n = np.array([1.0, 2.0, 7.0, 40.0, 400.0])
    S = np.array([0.3, 4.0, 12.0, 61.0, 380.0])
    np.testing.assert_allclose(chi2_median(n), chi2.ppf(0.5, n), rtol=1e-12)
    np.testing.assert_allclose(chi2_pvalue(S, n), chi2.sf(S, n), rtol=1e-12)
    np.testing.assert_allclose(chi2_pvalue(S, n, mu=2.0, phi=1.5), chi2.sf(S / (2.0 * 2.25), n / 2.25), rtol=1e-12)
    assert chi2_pvalue(np.array([0.0, 1.0]), np.array([0.0, 0.0])).tolist() == [1.0, 0.0]


def test_shape_parameters_at_a_hard_bound_are_named():
    """A box extent within AT_BOUND_TOLERANCE (scaled) of its smallest size (5 % of the
    size bound) or of the size bound is named with its side; interior ones are not."""
    from tacest.estimation.result import AT_BOUND_TOLERANCE, shape_params_at_bound
    from tacest.geometry.shapes import make_shape
    from tacest.geometry.shapes3d import make_shape_3d

    box3, bound = make_shape_3d("box"), 3.0  # scaled: size bound 3 L, smallest extent 0.15 L
    assert shape_params_at_bound(box3, [1.0, 0.8, 0.6], bound) == ()
    assert shape_params_at_bound(box3, [0.15, 0.8, 3.0], bound) == ("extent_x (lower)", "extent_z (upper)")
    assert shape_params_at_bound(box3, [0.15 + 2 * AT_BOUND_TOLERANCE, 0.8, 0.6], bound) == ()
    assert shape_params_at_bound(make_shape("box"), [0.5, 3.0], bound, names=["width", "height"]) == (
        "height (upper)",)


def test_a_shape_held_by_its_bound_is_marked_and_said_so():
    """The pushed box (10 cm wide, and 24 samples of one push that tell its height only
    through the dynamics) under a size bound of 8 cm: its height ends at the bound, so
    the fit is marked not valid whatever its residuals, and the one line says why; under
    the size bound of 30 cm nothing is at a bound and the fit is consistent."""
    from tacest.dims import estimate_runs
    from tacest.estimation.fitquality import quality_summary

    free = estimate_runs([pushed_box_run()], "box")
    assert free.success and free.consistent and "shape_at_bound" not in free.fit_quality
    run = pushed_box_run()
    held = estimate_runs([run.replace(prior={"size_bound": 0.08})], "box")
    assert held.success and held.consistent is False
    assert held.fit_quality["shape_at_bound"] and all(n.endswith("(upper)") for n in held.fit_quality["shape_at_bound"])
    assert np.ptp(held.vertices, axis=0).max() == pytest.approx(0.08, rel=1e-3)
    assert quality_summary(held.fit_quality).startswith("NOT a valid fit: the shape ended at a hard bound")


def test_samples_flagged_by_two_terms_count_once():
    """The local-misfit rule measures how much of the recording the flagged windows
    cover: two terms flagging the same 21 samples cover 21, not 42 (at one fast instant
    the contact, complementarity and dissipation terms flag the same window); windows
    of other runs never overlap."""
    from types import SimpleNamespace as W

    from tacest.estimation.fitquality import covered_samples

    same = [W(run=0, start=505, stop=526), W(run=0, start=505, stop=526), W(run=0, start=1019, stop=1040)]
    assert covered_samples(same) == 42
    assert covered_samples([W(run=0, start=0, stop=20), W(run=0, start=10, stop=30)]) == 30  # overlapping
    assert covered_samples([W(run=0, start=0, stop=20), W(run=1, start=0, stop=20)]) == 40  # two runs
    assert covered_samples([W(run=0, start=5, stop=10), W(run=0, start=0, stop=40)]) == 40  # nested
    assert covered_samples([]) == 0

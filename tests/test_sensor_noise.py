"""The sensors' noise measured from the data (tacest/estimation/sensor_noise.py).

Tolerances: from the ~2000 second differences per stream of these runs, the measured
sigma scatters by 1.6-3.1 % (one std over 40 noise draws, 2-D and 3-D; bias under 1.3 %);
the known-answer tests allow 10 % (more than three std).
"""

from __future__ import annotations

import numpy as np
import pytest

from tacest.estimation.config import EstimatorConfig
from tacest.estimation.sensor_noise import (MIN_DIFFERENCES, judged_config, judged_params, measured_noise, noise_report,
                                            rejudged)
from tacest.io.run import Run


def smooth_run(dim: int, T: int = 1000, F: int = 2, sig_force=0.0, sig_normal=0.0, sig_pos=0.0, seed=0,
               force=True) -> Run:
    """A run whose fingers touch throughout (a few gaps), with smooth true signals at
    100 Hz (a finger moving at ~5 cm/s, forces of a few N, normals turning at ~1 rad/s)
    plus white noise of the given sigmas (normals: tilted by sig_normal rad per
    perpendicular axis)."""
    rng = np.random.default_rng(seed)
    dt = 0.01
    t = np.arange(T) * dt
    fp = np.zeros((T, F, dim))
    fo = np.zeros((T, F, dim))
    nrm = np.zeros((T, F, dim))
    for f in range(F):
        for d in range(dim):
            fp[:, f, d] = 0.05 * np.sin(0.8 * t + f + d) + 0.1 * f
            fo[:, f, d] = 3.0 * np.sin(1.3 * t + 2 * d + f) + 1.0
        a = 1.0 * np.sin(0.9 * t + f)
        if dim == 2:
            nrm[:, f] = np.stack([np.cos(a), np.sin(a)], axis=1)
        else:
            b = 0.7 * np.cos(0.6 * t + f)
            nrm[:, f] = np.stack([np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), np.sin(b)], axis=1)
    fp += rng.normal(0, 1, fp.shape) * sig_pos
    fo += rng.normal(0, 1, fo.shape) * sig_force
    if dim == 2:
        e = rng.normal(0, 1, (T, F)) * sig_normal
        c, s = np.cos(e), np.sin(e)
        nrm = np.stack([c * nrm[..., 0] - s * nrm[..., 1], s * nrm[..., 0] + c * nrm[..., 1]], axis=-1)
    else:  # tilt about two axes perpendicular to the normal
        u = np.cross(nrm, np.array([0.0, 0.0, 1.0]))
        u /= np.linalg.norm(u, axis=-1, keepdims=True)
        v = np.cross(nrm, u)
        e = rng.normal(0, 1, (T, F, 2)) * sig_normal
        nrm = nrm + e[..., :1] * u + e[..., 1:] * v
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    contact = np.ones((T, F), np.uint8)
    contact[::97] = 0  # a few breaks: triples across them do not count
    nrm[contact == 0] = np.nan
    g = np.zeros(dim)
    g[-1] = -9.81
    return Run(dim=dim, dt=dt, time=t, gravity=g, source="test", finger_position=fp,
               finger_radius=np.full(F, 0.01), contact=contact, force=fo if force else None, normal=nrm)


@pytest.mark.parametrize("dim", [2, 3])
def test_known_noise_levels_are_measured(dim):
    """White noise of known sigma on smooth signals: each stream's sigma within 10 %."""
    run = smooth_run(dim, sig_force=0.2, sig_normal=0.08, sig_pos=3e-4)
    m = measured_noise([run])
    assert m["force"] == pytest.approx(0.2, rel=0.1)
    assert m["normal"] == pytest.approx(0.08, rel=0.1)
    assert m["position"] == pytest.approx(3e-4, rel=0.1)


def test_smooth_data_measure_far_below_the_defaults_and_change_nothing():
    """Noise-free smooth signals measure (nearly) zero noise: the configured levels are
    used, the residuals are judged as they are and the stds are not scaled."""
    run = smooth_run(2)
    m = measured_noise([run])
    cfg = EstimatorConfig()
    assert m["force"] < 0.01 * cfg.noise.force and m["normal"] < 0.01 * cfg.noise.normal
    report = noise_report([run], cfg)
    assert report["force"]["used"] == cfg.noise.force and report["position"]["setting"] == "noise.contact_gap"
    residuals = [{"force": np.ones(5), "dynamics": np.ones(5)}]
    assert rejudged(residuals, report) is residuals and judged_config(cfg, report) is cfg


def test_noisier_data_judge_the_fit_by_their_levels_and_only_those():
    """Force noise 0.2 N and normal noise 0.08 rad above the defaults (0.05 each): the
    force and normal terms are whitened by the measured levels (their squared residuals
    scaled by (0.05 / used)²), the contact term (position noise below contact_gap) and
    the model-error terms are left, and the judging config raises those two alone."""
    run = smooth_run(3, sig_force=0.2, sig_normal=0.08, sig_pos=1e-4)
    cfg = EstimatorConfig()
    report = noise_report([run], cfg)
    assert report["force"]["used"] == pytest.approx(0.2, rel=0.1)
    assert report["normal"]["used"] == pytest.approx(0.08, rel=0.1)
    assert report["position"]["used"] == cfg.noise.contact_gap
    residuals = [{"force": np.full(4, 2.0), "normal": np.full(4, 3.0), "contact": np.ones(4), "dynamics": np.ones(4)}]
    out = rejudged(residuals, report)
    np.testing.assert_allclose(out[0]["force"], 2.0 * (0.05 / report["force"]["used"]) ** 2, rtol=1e-12)
    np.testing.assert_allclose(out[0]["normal"], 3.0 * (0.05 / report["normal"]["used"]) ** 2, rtol=1e-12)
    assert out[0]["contact"] is residuals[0]["contact"] and out[0]["dynamics"] is residuals[0]["dynamics"]
    assert residuals[0]["force"][0] == 2.0  # the fit's own residuals are not changed
    judged = judged_config(cfg, report)
    assert (judged.noise.force, judged.noise.normal) == (report["force"]["used"], report["normal"]["used"])
    assert judged.noise.contact_gap == cfg.noise.contact_gap and judged.noise.process == cfg.noise.process
    assert noise_report([run], cfg.updated({"noise": {"from_data": False}})) == {}


def test_rescaling_the_force_rescales_its_measured_noise():
    """Invariance: forces in other units (x10) measure ten times the noise."""
    run = smooth_run(2, sig_force=0.05, seed=3)
    big = run.replace(force=run.force * 10.0)
    assert measured_noise([big])["force"] == pytest.approx(10 * measured_noise([run])["force"], rel=1e-9)


def test_too_few_samples_or_no_stream_measure_nothing():
    """Fewer than MIN_DIFFERENCES usable differences (components of second
    differences; here 2 fingers x 2 components x 4 triples), or no force stream: None, and the
    configured level is used."""
    short = smooth_run(2, T=MIN_DIFFERENCES // 4 + 1, sig_force=1.0, sig_normal=1.0, sig_pos=1.0)
    m = measured_noise([short])
    assert m == {"force": None, "normal": None, "position": None}
    report = noise_report([short], EstimatorConfig())
    assert report["force"]["measured"] is None and report["force"]["used"] == EstimatorConfig().noise.force
    assert measured_noise([smooth_run(2, force=False)])["force"] is None


def test_missing_finger_samples_do_not_count():
    """Samples flagged missing (placeholder values) are left out of every stream."""
    run = smooth_run(2, sig_force=0.05, sig_normal=0.05, sig_pos=2e-4, seed=5)
    clean = measured_noise([run])
    T, F = run.contact.shape
    mf = np.zeros((T, F), np.uint8)
    mf[100:200] = 1
    fp = run.finger_position.copy()
    fp[100:200] = 1e3  # placeholders far off: they would dominate if counted
    fo = run.force.copy()
    fo[100:200] = -1e3
    bad = run.replace(finger_position=fp, force=fo, missing_finger=mf, missing=mf.any(axis=1).astype(np.uint8))
    m = measured_noise([bad])
    assert m["position"] == pytest.approx(clean["position"], rel=0.1)
    assert m["force"] == pytest.approx(clean["force"], rel=0.1)


@pytest.mark.parametrize("dim", [2, 3])
def test_touch_alone_fits_whiten_by_the_measured_noise_pose_observed_fits_are_judged_by_it(dim):
    """Simulated runs with force noise 0.2 N and normal noise 0.08 rad.  Touch alone: the
    fit's own settings hold the measured levels (the report's ``fitted``), and its
    information uses the fit's parameters.  Pose observed: the fit keeps the configured
    levels, and the parameter vector of its information (judged_params) differs from the
    fit's only in the force and normal sigmas, which are the measured levels.  A run at
    the simulator's default noise (below the configured levels) changes nothing.
    Tolerance 25 %: two pokes give only ~100 contact samples (the measured sigmas of 1-3
    pokes scatter by about 10 %)."""
    from tacest.dims import record_sim
    from tacest.estimation.estimator import ImplicitEstimator
    from tacest.estimation.estimator3d import Estimator3D
    from tacest.sim.record import SimOptions

    make = ImplicitEstimator if dim == 2 else Estimator3D
    cfg = EstimatorConfig()
    touch = make([record_sim(SimOptions(dim=dim, seed=1, pokes=2, noise_force=0.2, noise_normal=0.08))], "box")
    rep = touch.sensor_noise
    assert rep["normal"]["used"] == pytest.approx(0.08, rel=0.25)
    assert (touch.config.noise.force, touch.config.noise.normal) == (rep["force"]["used"], rep["normal"]["used"])
    assert rep["force"]["fitted"] == rep["force"]["used"] > cfg.noise.force
    touch.p_final = touch.stage_params(touch.stages()[-1])  # as after a solve
    assert judged_params(touch) is touch.p_final
    if dim == 2:  # the 2-D simulator's forces are impulse / dt plus the noise: measured as drawn
        assert rep["force"]["used"] == pytest.approx(0.2, rel=0.25)

    seen = make([record_sim(SimOptions(dim=dim, seed=1, pokes=2, noise_force=0.2, noise_normal=0.08,
                                       observe_pose=0.0005))], "box")
    assert seen.config.noise == cfg.noise and seen.sensor_noise["force"]["fitted"] == cfg.noise.force
    seen.p_final = seen.stage_params(seen.stages()[-1])
    p, fit = np.asarray(judged_params(seen), float), np.asarray(seen.p_final, float)
    changed = p != fit
    assert changed.any()
    assert set(fit[changed]) <= {cfg.noise.force, cfg.noise.normal}
    assert set(p[changed]) <= {seen.sensor_noise["force"]["used"], seen.sensor_noise["normal"]["used"]}

    if dim == 2:
        quiet = make([record_sim(SimOptions(dim=2, seed=1, pokes=1))], "box")
        assert quiet.config.noise == cfg.noise
        quiet.p_final = quiet.stage_params(quiet.stages()[-1])
        assert judged_params(quiet) is quiet.p_final


def test_the_estimate_file_keeps_the_report_and_planning_weighs_by_its_levels(tmp_path):
    """The attr sensor_noise survives writing and reading; the planner's settings
    (config_of_estimate) take its used levels; a malformed report is one clear error."""
    import json

    import h5py

    from tacest.errors import TacestError
    from tacest.information.expected import config_of_estimate
    from tacest.io.estimate import read_estimate
    from reliability_files import make_run, truth_estimate

    run = make_run(tmp_path / "r.h5", pokes=1)
    path = truth_estimate([run], tmp_path / "e.h5")
    report = {"force": {"setting": "noise.force", "term": "force", "configured": 0.05, "measured": 0.2, "used": 0.2,
                        "fitted": 0.05},
              "normal": {"setting": "noise.normal", "term": "normal", "configured": 0.05, "measured": 0.01,
                         "used": 0.05}}
    with h5py.File(path, "a") as f:
        f.attrs["sensor_noise"] = json.dumps(report)
        f.attrs["config"] = json.dumps(EstimatorConfig().to_dict())
    est = read_estimate(path)
    assert json.loads(est.extra_attrs["sensor_noise"]) == report
    cfg = config_of_estimate(est)
    assert cfg.noise.force == 0.2 and cfg.noise.normal == 0.05
    with h5py.File(path, "a") as f:
        f.attrs["sensor_noise"] = json.dumps({"force": {"setting": "noise.force", "configured": 0.05, "used": -1}})
    with pytest.raises(TacestError, match="sensor_noise"):
        read_estimate(path)

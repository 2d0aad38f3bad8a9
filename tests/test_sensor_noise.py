"""The sensors' noise measured from the data (tacest/estimation/sensor_noise.py).

Tolerances: from the ~2000 second differences per stream of these runs, the measured
sigma scatters by 1.6-3.1 % (one std over 40 noise draws, 2-D and 3-D; bias under 1.3 %);
the known-answer tests allow 10 % (more than three std).
"""

from __future__ import annotations

import numpy as np
import pytest

from tacest.estimation.config import EstimatorConfig
from tacest.estimation.sensor_noise import MIN_DIFFERENCES, measured_noise, with_measured_noise
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
    """Noise-free smooth signals measure (nearly) zero noise: the configured levels stay,
    the config object is the very same, and the report says what was measured."""
    run = smooth_run(2)
    m = measured_noise([run])
    cfg = EstimatorConfig()
    assert m["force"] < 0.01 * cfg.noise.force and m["normal"] < 0.01 * cfg.noise.normal
    out, report = with_measured_noise([run], cfg)
    assert out is cfg
    assert report["force"]["used"] == cfg.noise.force and report["position"]["setting"] == "noise.contact_gap"


def test_noisier_data_raise_the_levels_and_only_those():
    """Force noise 0.2 N and normal noise 0.08 rad above the defaults (0.05 each) are
    raised to what was measured; a position noise below contact_gap leaves it."""
    run = smooth_run(3, sig_force=0.2, sig_normal=0.08, sig_pos=1e-4)
    cfg = EstimatorConfig()
    out, report = with_measured_noise([run], cfg)
    assert out.noise.force == pytest.approx(0.2, rel=0.1) and out.noise.force == report["force"]["used"]
    assert out.noise.normal == pytest.approx(0.08, rel=0.1)
    assert out.noise.contact_gap == cfg.noise.contact_gap
    assert out.noise.process == cfg.noise.process  # model-error settings are not touched
    off, report_off = with_measured_noise([run], cfg.updated({"noise": {"from_data": False}}))
    assert off.noise.force == cfg.noise.force and report_off == {}


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
    cfg = EstimatorConfig()
    out, report = with_measured_noise([short], cfg)
    assert out is cfg and report["force"]["measured"] is None
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

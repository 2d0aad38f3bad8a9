"""The sensors' noise levels as the data show them, against the configured ones.

The estimator whitens each measured stream by a configured noise level ([noise] force,
normal, contact_gap).  SPEC's run files do not carry their sensors' noise, and a rig or a
simulator may be noisier than the defaults assume; whitened by too small a sigma, a right
fit fails its goodness-of-fit test and reports error bars too small by the same factor.

So before a fit the noise of each stream is measured from the data alone, where the
signal is smooth at the sample rate: with x_t = s_t + e_t (e white, sigma per component)
the second difference x_{t+1} - 2 x_t + x_{t-1} is the noise's, of variance 6 sigma²,
plus the signal's s'' dt², small at 100 Hz but for the few samples of an impact or of a
finger crossing an edge.  A median (robust to those) of the squared second differences
gives sigma:

    sigma² = median(|d2|²) / (6 · median χ²(k))

with k the components per difference: 1 for each force and position component, D - 1
for a unit normal (its second difference projected off the middle sample's normal: the
angles, D = 2 or 3).  Only consecutive triples where the stream is there count: forces
and normals in contact, positions where the finger is not missing.  On tacest's own
simulator (force 0.02 N, normal 0.02 rad, position 0.1 mm) this gives 0.025-0.027 N,
0.020-0.021 rad and 0.10-0.11 mm; with 0.2 N and 0.08 rad, 0.21 N and 0.085 rad.

Where a stream is noisier than its setting, the larger level is used
(:func:`settings_for`):

- in runs without pose observations (touch alone: the streams are the data), the fit
  itself whitens by it: on 2-D dynamic pokes with force noise 0.2 N (seed 14) the fit
  whitened by 0.05 N fell into a light-object basin (22 mm, mass 92 % low, marked
  consistent), whitened by the measured 0.2 N it found the box (4.5 mm, mass exact);
- in runs with pose observations (motion capture anchors the fit), the fit keeps the
  configured levels, whose balance against the pose terms was tuned: raised inside the
  fit (force 0.05 -> 0.08 N on a MuJoCo recording), the plain fit of a box with an
  unmodelled centre-of-mass offset no longer converged in 1000 iterations, where it had
  in 247.  There the larger level judges the fit instead: the goodness-of-fit test
  whitens the term by it (:func:`rejudged`: the force, normal and contact terms are
  linear in 1/sigma, so their squared residuals scale exactly by (fitted / used)²), and
  the observed information, so every reported std, is computed at the fit with it
  (:func:`judged_params`).

A stream quieter than its setting changes nothing.  The fingertip position's noise is
the floor of the contact gap's sigma (the gap is measured through that position).  What
was measured and used is the estimate's attr ``sensor_noise`` (docs/formats.md);
``noise.from_data = false`` keeps the configured levels.
"""

from __future__ import annotations

import copy
import logging

import numpy as np

log = logging.getLogger(__name__)

#: fewest second differences a level is measured from (fewer: not measured)
MIN_DIFFERENCES = 20
#: the configured setting (noise.<key>) that each measured stream can raise, with its unit
STREAMS = {"force": ("force", "N"), "normal": ("normal", "rad"), "position": ("contact_gap", "m")}
#: the loss term each stream's level whitens (tacest.estimation.floor.TERMS)
TERM_OF = {"force": "force", "normal": "normal", "position": "contact"}


def _consecutive(valid: np.ndarray) -> np.ndarray:
    """(T - 2,) bool: the triples (t - 1, t, t + 1) valid at all three samples."""
    return valid[:-2] & valid[1:-1] & valid[2:]


def _second_differences(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(n, C) second differences of the rows of x (T, C) over the valid triples."""
    if len(x) < 3:
        return np.zeros((0, x.shape[1]))
    d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return d2[_consecutive(valid)]


def _sigma(squares: np.ndarray, dof: int):
    """sigma from squared second-difference norms of ``dof`` components each, or None
    when there are fewer than MIN_DIFFERENCES of them."""
    from scipy.special import chdtri  # chi2.ppf(q, k) = chdtri(k, 1 - q)

    squares = squares[np.isfinite(squares)]
    if squares.size < MIN_DIFFERENCES:
        return None
    return float(np.sqrt(np.median(squares) / (6.0 * float(chdtri(dof, 0.5)))))


def measured_noise(runs: list) -> dict:
    """{"force" N, "normal" rad, "position" m: sigma per component (per angle for
    normals) or None}, pooled over the runs' fingers and samples (module doc)."""
    pooled = {"force": [], "normal": [], "position": []}
    for run in runs:
        if not run.n_fingers:
            continue
        ok = ~np.asarray(run.finger_missing_mask, bool)  # (T, F)
        on = np.asarray(run.contact, bool) & ok
        for f in range(run.n_fingers):
            pooled["position"].append(_second_differences(run.finger_position[:, f], ok[:, f]).reshape(-1) ** 2)
            if run.force is not None:
                pooled["force"].append(_second_differences(run.force[:, f], on[:, f]).reshape(-1) ** 2)
            n = run.normal[:, f]
            valid = on[:, f] & np.all(np.isfinite(n), axis=1)
            d2 = _second_differences(np.where(valid[:, None], n, 0.0), valid)
            mid = n[1:-1][_consecutive(valid)]
            tangent = d2 - np.sum(d2 * mid, axis=1, keepdims=True) * mid
            pooled["normal"].append(np.sum(tangent ** 2, axis=1))
    dims = {int(r.dim) for r in runs}
    dof_normal = (max(dims) if dims else 2) - 1
    out = {}
    for key, parts in pooled.items():
        squares = np.concatenate(parts) if parts else np.zeros(0)
        out[key] = _sigma(squares, dof_normal if key == "normal" else 1)
    return out


def noise_report(runs: list, config) -> dict:
    """{stream: {"setting", "term", "configured", "measured", "used", "fitted"}}: per
    stream of STREAMS the configured level, the measured one (None: too few samples),
    the larger, which judges the fit, and the one the fit whitens by (here the
    configured; :func:`settings_for` sets it) (module doc); {} with ``noise.from_data``
    false."""
    if not config.noise.from_data:
        return {}
    measured = measured_noise(runs)
    report = {}
    for stream, (setting, _) in STREAMS.items():
        configured = float(getattr(config.noise, setting))
        m = measured[stream]
        used = configured if m is None else max(configured, m)
        report[stream] = {"setting": f"noise.{setting}", "term": TERM_OF[stream], "configured": configured,
                          "measured": m, "used": used, "fitted": configured}
    return report


def settings_for(runs: list, config) -> tuple:
    """(the settings the fit of ``runs`` uses, the noise report): without pose
    observations the used levels whiten the fit itself, with them only the judging
    (module doc); the report's ``fitted`` says which level the fit whitened by."""
    report = noise_report(runs, config)
    in_fit = not any(r.pose_obs is not None for r in runs)
    for stream, v in report.items():
        if v["used"] > v["configured"]:
            if in_fit:
                v["fitted"] = v["used"]
            unit = STREAMS[stream][1]
            log.info(f"the {stream} readings are noisier than {v['setting']} = {v['configured']:.3g} {unit}: "
                     f"{v['used']:.3g} {unit} measured sample to sample; "
                     + ("the fit whitens them by that" if in_fit else "the fit is judged by that"))
    return (judged_config(config, report) if in_fit else config), report


def rejudged(residuals: list, report: dict) -> list:
    """Per run {term: (T,) 0.5·‖r‖²} with the force, normal and contact terms whitened by
    the report's ``used`` levels instead of those the fit used (``fitted``; copies; the
    other terms, and terms the fit already whitened so, as they are)."""
    scale = {v["term"]: (v["fitted"] / v["used"]) ** 2 for v in report.values() if v["used"] > v["fitted"]}
    if not scale:
        return residuals
    return [{t: (np.asarray(r, float) * scale[t] if t in scale else r) for t, r in res.items()} for res in residuals]


def judged_config(config, report: dict):
    """``config`` with noise.force, noise.normal and noise.contact_gap at the report's
    ``used`` levels where those are larger than its own (the config itself where none
    is)."""
    raised = {}
    for v in report.values():
        name = v["setting"].split(".", 1)[1]
        if v["used"] > float(getattr(config.noise, name)):
            raised[name] = v["used"]
    return config.updated({"noise": raised}) if raised else config


def judged_params(est) -> np.ndarray:
    """The NLP parameter vector of the final stage of estimator ``est`` (2-D
    ImplicitEstimator or Estimator3D, after its solve) with the noise levels that judge
    the fit: its observed information then weighs each stream by the noise its data
    show.  ``est.p_final`` where nothing is raised.  (Where contact_gap is raised, the
    smoothing of max(phi, 0), in contact-gap sigmas, widens with it too.)"""
    cfg = judged_config(est.config, est.sensor_noise)
    if cfg is est.config:
        return est.p_final
    clone = copy.copy(est)
    clone.config = cfg
    return clone.stage_params(clone.stages()[-1])

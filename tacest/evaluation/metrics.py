"""Score an estimate against the truth of a simulated run (``tacest eval``).

Metrics (all defined in docs/evaluation.md):

    chamfer               m    Chamfer distance of the placed shapes, mean over time
    chamfer_max           m    its largest value over the evaluated frames
    chamfer_body          m    Chamfer distance of the shapes alone, best rigid alignment
    pose_position_rmse    m    RMS over samples of |p_est - p_true| (centre of mass)
    pose_angle_rmse       rad  RMS over samples of the orientation error
                               (2-D wrapped angle difference, 3-D geodesic angle)
    mass_rel, friction_ground_rel, friction_finger_rel, inertia_rel
                          1    |est - true| / |true|; inertia 3-D: see _inertia_rel
    n_samples             1    samples of the run
    solver_status         str  what the estimator reported

A relative error is NaN (JSON null) where the truth lacks the value (not finite).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tacest.errors import TacestError
from tacest.geometry.chamfer import MAX_FRAMES, chamfer_body, chamfer_placed_series
from tacest.geometry.transforms import pose_angle_error

#: Keys every report has (SPEC's list plus ours), in display order.
METRIC_KEYS = ("chamfer", "chamfer_max", "chamfer_body", "pose_position_rmse", "pose_angle_rmse",
               "mass_rel", "inertia_rel", "friction_ground_rel", "friction_finger_rel")
PARAM_KEYS = ("mass", "inertia", "friction_ground", "friction_finger")


def match_run(est, truth_run, truth_sha256: str | None = None, run_index: int | None = None):
    """Which of the estimate's runs belongs to ``truth_run``.

    Order: an explicit ``run_index``; the run whose ``source_sha256`` equals
    ``truth_sha256``; the run whose ``source_file`` names the same file (resolved path,
    else a unique base name); run 0 when it has as many samples as the truth.

    Returns (index, how) with how in {"run-index", "sha256", "source_file", "length"}.
    Raises TacestError when nothing matches.
    """
    n = len(est.runs)
    what = est.filename or "estimate"
    if n == 0:
        raise TacestError(f"{what}: /runs holds no estimated trajectory")
    if run_index is not None:
        if not 0 <= int(run_index) < n:
            raise TacestError(f"{what}: no run {run_index} (it holds {n} run{'s' if n != 1 else ''}: 0..{n - 1})")
        return int(run_index), "run-index"
    if truth_sha256:
        hits = [i for i, r in enumerate(est.runs) if r.source_sha256 == truth_sha256]
        if hits:
            return hits[0], "sha256"
    if truth_run.filename:
        tpath = Path(truth_run.filename)
        for i, r in enumerate(est.runs):
            if r.source_file and _same_file(r.source_file, tpath):
                return i, "source_file"
        names = [i for i, r in enumerate(est.runs) if r.source_file and Path(r.source_file).name == tpath.name]
        if len(names) == 1:
            return names[0], "source_file"
    T = truth_run.n_samples
    if est.runs[0].pose.shape[0] == T:
        return 0, "length"
    src = truth_run.filename or "the truth run"
    raise TacestError(f"{what}: none of its {n} run(s) comes from {src} (no matching source_sha256 "
                      f"or source_file) and run 0 has {est.runs[0].pose.shape[0]} samples, not {T}; "
                      "pick one with --run-index")


def _same_file(a, b: Path) -> bool:
    try:
        return Path(a).resolve() == b.resolve()
    except OSError:
        return False


def evaluate(est, truth_run, run_index: int = 0, n_samples=None, max_frames: int = MAX_FRAMES,
             return_series: bool = False):
    """Compare ``est`` (tacest.io.estimate.Estimate) with ``truth_run.truth``.

    est.runs[run_index] must be the estimated trajectory of ``truth_run`` (see
    :func:`match_run`).  n_samples: boundary samples per shape for the Chamfer
    distances (default: tacest.geometry.chamfer.default_samples); max_frames: the
    placed Chamfer distance is averaged over every k-th sample, at most this many.

    Returns a dict (see the module docstring; floats in SI units, NaN where not
    defined), and with ``return_series`` also a dict of per-frame arrays:
    ``frames`` (F,) sample indices, ``time`` (F,) s, ``chamfer`` (F,) m,
    ``position_error`` (F,) m, ``angle_error`` (F,) rad.

    Raises TacestError: no /truth, different dimensions, lengths that differ, an
    index out of range, degenerate shapes.
    """
    what = truth_run.filename or "truth run"
    if truth_run.truth is None:
        raise TacestError(f"{what}: has no /truth (only simulated runs recorded with truth can be evaluated)")
    if est.dim != truth_run.dim:
        raise TacestError(f"{est.filename or 'estimate'} is {est.dim}-D but {what} is {truth_run.dim}-D")
    n_runs = len(est.runs)
    if not 0 <= run_index < n_runs:
        raise TacestError(f"{est.filename or 'estimate'}: no run {run_index} (it holds {n_runs})")
    tr = truth_run.truth
    D = est.dim
    pose_est = np.asarray(est.runs[run_index].pose, float)
    pose_true = np.asarray(tr.pose, float)
    if pose_est.shape != pose_true.shape:
        raise TacestError(f"{est.filename or 'estimate'}: run {run_index} has {pose_est.shape[0]} samples "
                          f"but {what} has {pose_true.shape[0]}; they are not the same run")
    try:
        frames, ch = chamfer_placed_series(est.vertices, pose_est, tr.vertices, pose_true,
                                           n_samples=n_samples, max_frames=max_frames)
        ch_body = chamfer_body(est.vertices, tr.vertices, n_samples=n_samples)
    except TacestError as exc:
        raise TacestError(f"{est.filename or 'estimate'} vs {what}: {exc}") from None

    pos_err = np.linalg.norm(pose_est[:, :D] - pose_true[:, :D], axis=1)
    ang_err = pose_angle_error(pose_est, pose_true, D)
    params = {}
    for k in PARAM_KEYS:
        e, t = est.params.get(k), getattr(tr, k)
        rel = _inertia_rel(e, t, D) if k == "inertia" else _rel(e, t)
        ident = est.identifiable.get(k) if isinstance(est.identifiable, dict) else None
        params[k] = {"estimate": _plain(e), "truth": _plain(t), "rel": rel,
                     "identifiable": None if ident is None else bool(ident),
                     "sigmas": _sigmas(e, t, est.std.get(k))}
    report = {
        "chamfer": float(np.mean(ch)),
        "chamfer_max": float(np.max(ch)),
        "chamfer_body": float(ch_body),
        "shape_std": _finite_scalar(est.std.get("shape")),
        "chamfer_body_sigmas": _sigmas(ch_body, 0.0, est.std.get("shape")),
        "pose_position_rmse": float(np.sqrt(np.mean(pos_err ** 2))),
        "pose_angle_rmse": float(np.sqrt(np.mean(ang_err ** 2))),
        "mass_rel": params["mass"]["rel"],
        "inertia_rel": params["inertia"]["rel"],
        "friction_ground_rel": params["friction_ground"]["rel"],
        "friction_finger_rel": params["friction_finger"]["rel"],
        "n_samples": int(pose_true.shape[0]),
        "n_frames": int(len(frames)),
        "solver_status": str(est.solver_status),
        "success": bool(est.success),
        "fit_consistent": est.consistent,
        "dim": int(D),
        "shape": str(est.shape),
        "run_index": int(run_index),
        "estimate_file": est.filename,
        "truth_file": truth_run.filename,
        "truth_effects": [e.get("name", "?") if isinstance(e, dict) else str(e) for e in tr.effects],
        "params": params,
    }
    if not return_series:
        return report
    series = {"frames": frames, "time": np.asarray(truth_run.time, float)[frames], "chamfer": ch,
              "position_error": pos_err[frames], "angle_error": ang_err[frames]}
    return report, series


def evaluate_files(est_path, truth_path, run_index: int | None = None, return_series=False):
    """Read both files, match the run (:func:`match_run`) and :func:`evaluate`.

    Returns what :func:`evaluate` returns, with ``matched_by`` added to the report,
    plus (est, run) so callers can plot without reading again:
    ``(report, est, run)`` or ``(report, series, est, run)``.
    """
    from tacest.io.estimate import read_estimate
    from tacest.io.h5util import sha256_file
    from tacest.io.run import read_run

    est = read_estimate(est_path)
    run = read_run(truth_path)
    if run.truth is None:
        raise TacestError(f"{truth_path}: has no /truth (only simulated runs recorded with truth can be evaluated)")
    index, how = match_run(est, run, truth_sha256=sha256_file(truth_path), run_index=run_index)
    out = evaluate(est, run, index, return_series=return_series)
    report = out[0] if return_series else out
    report["matched_by"] = how
    return (report, out[1], est, run) if return_series else (report, est, run)


# ---------------------------------------------------------------------------------
# helpers


def _finite_scalar(v):
    try:
        a = np.asarray(v, float)
    except (TypeError, ValueError):
        return None
    if a.size != 1 or not np.isfinite(a).all():
        return None
    return float(a.reshape(()))


def _sigmas(est, true, std):
    """|est - true| / std of a scalar parameter (its error in units of its stated
    one-sigma uncertainty: ~68 % of calibrated estimates are within 1); None where
    either value or the std is missing, not finite or not positive."""
    e, t, s = _finite_scalar(est), _finite_scalar(true), _finite_scalar(std)
    if e is None or t is None or s is None or s <= 0:
        return None
    return abs(e - t) / s


def _rel(est, true) -> float:
    """|est - true| / |true|; NaN when either is missing or not finite, or true = 0."""
    e, t = _finite_scalar(est), _finite_scalar(true)
    if e is None or t is None or t == 0.0:
        return math.nan
    return abs(e - t) / abs(t)


def _as_tensor(v):
    """3-D inertia as a (3, 3) array: 9 numbers, 3 (principal, diagonal) or 1
    (isotropic); None if missing or not finite."""
    if v is None:
        return None
    try:
        a = np.asarray(v, float).reshape(-1)
    except (TypeError, ValueError):
        return None
    if not np.all(np.isfinite(a)):
        return None
    if a.size == 9:
        M = a.reshape(3, 3)
        return 0.5 * (M + M.T)
    if a.size == 3:
        return np.diag(a)
    if a.size == 1:
        return np.eye(3) * a[0]
    return None


def _inertia_rel(est, true, dim) -> float:
    """Relative inertia error.  2-D: |I_est - I_true| / I_true.

    3-D: ``min_Q ||Q I_est Q^T - I_true||_F / ||I_true||_F`` over rotations Q, i.e.
    the Frobenius-norm relative error once the two body frames are lined up, which
    equals ``||sort(eig I_est) - sort(eig I_true)|| / ||eig I_true||`` (Hoffman-Wielandt).
    The estimate's body axes need not be the truth's, so comparing tensors entry by
    entry would charge a mere relabelling of axes as error.
    """
    if dim == 2:
        return _rel(est, true)
    E, T = _as_tensor(est), _as_tensor(true)
    if E is None or T is None:
        return math.nan
    lt = np.linalg.eigvalsh(T)
    nt = float(np.linalg.norm(lt))
    if nt == 0.0:
        return math.nan
    return float(np.linalg.norm(np.linalg.eigvalsh(E) - lt) / nt)


def _plain(v):
    """A JSON-friendly copy of a parameter value (float, list, or None)."""
    if v is None:
        return None
    a = np.asarray(v, float)
    if a.size == 1:
        return float(a.reshape(()))
    return a.tolist()


def to_jsonable(obj):
    """Recursively turn a report into JSON-safe values: NaN/inf -> None, numpy -> Python."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    return obj


def format_report(report: dict) -> str:
    """A readable multi-line table of a report (what ``tacest eval`` prints)."""
    lines = []
    est_name = report.get("estimate_file") or "estimate"
    truth_name = report.get("truth_file") or "truth"
    how = report.get("matched_by")
    lines.append(f"estimate  {est_name}  (run {report['run_index']}" + (f", matched by {how})" if how else ")"))
    lines.append(f"truth     {truth_name}  ({report['dim']}-D, {report['n_samples']} samples"
                 + (f", effects: {', '.join(report['truth_effects'])}" if report.get("truth_effects") else "")
                 + ")")
    fit = {True: ";  fit consistent with its data", False: ";  fit NOT consistent with its data (error bars "
           "not to be trusted)"}.get(report.get("fit_consistent"), "")
    lines.append(f"solver    {report['solver_status']}" + ("" if report.get("success") else "  (not a success)")
                 + f";  shape {report['shape']}{fit}")
    lines.append("")
    rows = [
        ("chamfer", _mm(report["chamfer"]), f"placed shapes, mean over {report['n_frames']} frames"),
        ("chamfer_max", _mm(report["chamfer_max"]), "placed shapes, worst frame"),
        ("chamfer_body", _mm(report["chamfer_body"]), "shapes alone, best rigid alignment"
         + (f" ({report['chamfer_body_sigmas']:.1f} x the shape's std {_mm(report['shape_std'])})"
            if report.get("chamfer_body_sigmas") is not None else "")),
        ("pose_position_rmse", _mm(report["pose_position_rmse"]), "centre of mass"),
        ("pose_angle_rmse", _angle(report["pose_angle_rmse"]), "orientation"),
    ]
    w = max(len(r[0]) for r in rows)
    lines.append(f"{'metric':<{w}}  {'value':>22}  note")
    for name, val, note in rows:
        lines.append(f"{name:<{w}}  {val:>22}  {note}")
    lines.append("")
    units = {"mass": "kg", "inertia": "kg m2", "friction_ground": "", "friction_finger": ""}
    prow = [(k, _val(p["estimate"], units[k]), _val(p["truth"], units[k]),
             _pct(p["rel"]) + (f"  ({p['sigmas']:.1f} sigma)" if p.get("sigmas") is not None else "")
             + ("  (not identifiable: the prior's value)" if p.get("identifiable") is False else ""))
            for k, p in ((k, report["params"][k]) for k in PARAM_KEYS)]
    we = max(12, *(len(r[1]) for r in prow))
    wt = max(12, *(len(r[2]) for r in prow))
    lines.append(f"{'parameter':<{w}}  {'estimate':>{we}}  {'truth':>{wt}}  rel. error")
    for k, e, t, rel in prow:
        lines.append(f"{k:<{w}}  {e:>{we}}  {t:>{wt}}  {rel}")
    if report["dim"] == 3:
        lines.append("(3-D inertia shown as principal moments; its error compares them, see docs/evaluation.md)")
    return "\n".join(lines)


def _mm(v):
    return "n/a" if v is None or not math.isfinite(v) else f"{v * 1e3:.3f} mm"


def _angle(v):
    return "n/a" if v is None or not math.isfinite(v) else f"{v:.4f} rad ({math.degrees(v):.2f} deg)"


def _pct(v):
    return "n/a" if v is None or not math.isfinite(v) else f"{100.0 * v:.1f} %"


def _val(v, unit):
    if v is None:
        return "n/a"
    a = np.asarray(v, float)
    if a.size == 1:
        x = float(a.reshape(()))
        return "n/a" if not math.isfinite(x) else (f"{x:.4g} {unit}".strip())
    T = _as_tensor(a)
    if T is None:
        return "n/a"
    ev = np.linalg.eigvalsh(T)
    return "[" + ", ".join(f"{x:.3g}" for x in ev) + "]" + (f" {unit}" if unit else "")

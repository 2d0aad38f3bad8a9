"""Benchmark the estimators (``estimate_runs``, method implicit and shooting) on simulated runs.

    .venv/bin/python benchmarks/bench_estimate.py [--seeds 10] [--cases box,polygon,noforce,scaling]
                                                  [--methods implicit,shooting] [--timeout 600]
                                                  [--reach M] [--quiet] [--json OUT.json]

Cases (2-D, ``record_sim``; 6 pokes, force noise 0.02 N, about 8-10 s at 100 Hz each):

- ``box``: a random box per seed, estimated as ``box``;
- ``polygon``: a random convex polygon of 5-7 vertices (``polygon:{5 + seed % 3}``),
  estimated as ``polygon:8``;
- ``noforce``: a random box recorded without the force stream (contact and normal only),
  estimated as ``box`` (the mass is then not identifiable and is not scored);
- ``scaling``: one recording (box, seed 0, 12 pokes) cut to T = 200, 400, 800, 1600
  samples: wall time of each and its ratio to T = 200.

Every estimate runs in its own subprocess (this script with ``--worker``) with a time
limit, so that one hung solve cannot stall the benchmark; a SolveFailedError, any other
error and a timeout all count as failures and are reported with their reason.  Wall time
is measured in the worker around ``estimate_runs`` (NLP construction included, Python
start-up and imports not).

Printed per case and method: runs and failures, median Chamfer distance ``chamfer``
(mm, the placed shapes over time, tacest.evaluation.metrics), median relative errors of
mass and of ground and finger friction, median wall time, median recording duration and
the median ratio of the two; then the targets with PASS / FAIL: boxes chamfer <= 3 mm and
mass and friction errors <= 15 %, polygons <= 5 mm, no-force boxes <= 6 mm, wall time
<= recording duration, and scaling no worse than linear (time(T) / time(200) <= T / 200).
Medians are over the successful runs; a target counts as met only if no run failed.
The exit status is 0 whether or not the targets are met (1 only for bad arguments).
``--reach M`` sets the estimator's ``noise.complementarity_reach`` (m, 0: off) for
every estimate (the shooting method has no complementarity residual and ignores it), to
compare the estimator with and without it on the same recordings.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CASES = ("box", "polygon", "noforce", "scaling")
METHODS = ("implicit", "shooting")
SCALING_T = (200, 400, 800, 1600)
#: targets (the issue's figures): median chamfer (m) per case; relative errors; time ratios
TARGET_CHAMFER = {"box": 3e-3, "polygon": 5e-3, "noforce": 6e-3}
TARGET_REL = 0.15
TARGET_REALTIME = 1.0
REL_KEYS = ("mass_rel", "friction_ground_rel", "friction_finger_rel")


# ------------------------------------------------------------------------------------
# worker: one estimate in its own process


def worker(run_path: str, shape: str, method: str, reach: str = "") -> dict:
    """Estimate one run file (2-D, or 3-D: estimate_runs hands those to the 3-D
    estimator) and score it against its truth; never raises.  ``starts``: the solves
    from each starting shape (the estimate's attr ``starts``); ``reach``: the
    estimator's noise.complementarity_reach (m; empty: the default configuration)."""
    from tacest.estimation.config import EstimatorConfig
    from tacest.errors import TacestError
    from tacest.dims import estimate_runs
    from tacest.evaluation.metrics import evaluate, match_run
    from tacest.io.h5util import sha256_file
    from tacest.io.run import read_run

    out = {"ok": False, "status": "", "error": "", "wall": math.nan}
    run = read_run(run_path)
    out["samples"] = run.n_samples
    out["duration"] = run.n_samples * run.dt
    t0 = time.perf_counter()
    try:
        config = EstimatorConfig().with_reach(float(reach)) if reach else None
        est = estimate_runs([run], shape, config=config, method=method)
    except TacestError as exc:
        out["wall"] = time.perf_counter() - t0
        m = re.search(r": (\w+) after \d+ iterations", str(exc))  # IPOPT's status, when it says it
        out["status"] = type(exc).__name__ + (f" ({m.group(1)})" if m else "")
        out["error"] = str(exc)
        return out
    except Exception as exc:  # noqa: BLE001 - a crash is a failure to report, not to hide
        out["wall"] = time.perf_counter() - t0
        out["status"] = f"crash: {type(exc).__name__}"
        out["error"] = str(exc)
        return out
    out["wall"] = time.perf_counter() - t0
    out.update(ok=bool(est.success), status=str(est.solver_status), iterations=int(est.iterations),
               objective=float(est.objective), starts=json.loads(est.extra_attrs.get("starts", "[]")))
    if not est.success:
        out["error"] = "estimate returned without success"
        return out
    idx, _ = match_run(est, run, truth_sha256=sha256_file(run_path))
    rep = evaluate(est, run, idx)
    for k in ("chamfer", "chamfer_body", "pose_position_rmse", "pose_angle_rmse", *REL_KEYS):
        v = rep[k]
        out[k] = None if v is None or (isinstance(v, float) and math.isnan(v)) else float(v)
    out["identifiable"] = {k: bool(v) for k, v in est.identifiable.items()}
    return out


def run_job(run_path: Path, shape: str, method: str, timeout: float, reach: float | None = None) -> dict:
    """The worker in a subprocess with a time limit (killed when it runs over); ``reach``
    None: the estimator's default noise.complementarity_reach."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(run_path), shape, method,
           "" if reach is None else repr(reach)]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"ok": False, "status": "timeout", "error": f"no result within {timeout:.0f} s",
                "wall": time.perf_counter() - t0}
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {"ok": False, "status": f"worker exit {proc.returncode}", "error": tail,
                "wall": time.perf_counter() - t0}
    return json.loads(lines[-1])


# ------------------------------------------------------------------------------------
# recordings


def record(case: str, seed: int, directory: Path) -> tuple[Path, str]:
    """Record the case's run for ``seed`` into directory; returns (path, estimation shape)."""
    from tacest.io.run import write_run
    from tacest.sim.record import SimOptions, record_sim

    if case == "box":
        opts, shape = SimOptions(object_spec="box", pokes=6, noise_force=0.02, seed=seed), "box"
    elif case == "polygon":
        opts, shape = SimOptions(object_spec=f"polygon:{5 + seed % 3}", pokes=6, noise_force=0.02, seed=seed), \
            "polygon:8"
    elif case == "noforce":
        opts = SimOptions(object_spec="box", pokes=6, noise_force=0.02, seed=seed, force_stream=False)
        shape = "box"
    else:
        raise ValueError(case)
    path = directory / f"{case}_{seed}.h5"
    write_run(record_sim(opts), path)
    return path, shape


def cut_run(run, T: int):
    """The first T samples of a run (actions clipped to them)."""
    from tacest.io.run import Actions, Truth

    def cut(a):
        return None if a is None else np.asarray(a)[:T]

    actions = None
    if run.actions is not None:
        seg = np.asarray(run.actions.segments)
        keep = seg[:, 0] < T
        actions = Actions(segments=np.minimum(seg[keep], T), params=np.asarray(run.actions.params)[keep],
                          kind=run.actions.kind, names=run.actions.names)
    truth = None
    if run.truth is not None:
        tr = run.truth
        truth = Truth(pose=cut(tr.pose), vertices=tr.vertices, mass=tr.mass, inertia=tr.inertia,
                      friction_ground=tr.friction_ground, friction_finger=tr.friction_finger, effects=tr.effects)
    return run.replace(time=cut(run.time), finger_position=cut(run.finger_position), contact=cut(run.contact),
                       force=cut(run.force), normal=cut(run.normal), pose_obs=cut(run.pose_obs),
                       missing=cut(run.missing), actions=actions, truth=truth, filename=None)


def record_scaling(directory: Path) -> list[tuple[int, Path]]:
    from tacest.io.run import write_run
    from tacest.sim.record import SimOptions, record_sim

    full = record_sim(SimOptions(object_spec="box", pokes=12, noise_force=0.02, seed=0))
    out = []
    for T in SCALING_T:
        if T > full.n_samples:
            raise SystemExit(f"scaling: the recording has only {full.n_samples} samples, fewer than {T}")
        path = directory / f"scaling_{T}.h5"
        write_run(cut_run(full, T), path)
        out.append((T, path))
    return out


# ------------------------------------------------------------------------------------
# summaries


def _median(values):
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(vals)) if vals else math.nan


def median_figures(jobs: list[dict], rel_keys=REL_KEYS) -> dict:
    """Failures and medians of a case's jobs: Chamfer and ``rel_keys`` over the
    successful ones (NaN for a key not in ``rel_keys``), wall time, recording duration
    and their ratio over all that have them."""
    good = [j for j in jobs if j.get("ok")]
    s = {"runs": len(jobs), "failures": len(jobs) - len(good),
         "failure_reasons": sorted({j["status"] for j in jobs if not j.get("ok")}),
         "chamfer": _median([j.get("chamfer") for j in good]),
         "wall": _median([j.get("wall") for j in jobs if np.isfinite(j.get("wall", math.nan))]),
         "duration": _median([j.get("duration") for j in jobs if j.get("duration")]),
         "realtime_ratio": _median([j["wall"] / j["duration"] for j in jobs
                                    if j.get("duration") and np.isfinite(j.get("wall", math.nan))])}
    for k in REL_KEYS:
        s[k] = _median([j.get(k) for j in good]) if k in rel_keys else math.nan
    return s


def accuracy_targets(s: dict, chamfer_limit: float, rel_keys=REL_KEYS) -> list:
    """(target, measured, met) of the median Chamfer (<= chamfer_limit, m) and of each
    of ``rel_keys`` (<= TARGET_REL); met only if no run failed."""
    no_fail = s["failures"] == 0
    targets = [(f"median chamfer <= {chamfer_limit * 1e3:.0f} mm", f"{_fmt(s['chamfer'], 1e3, 2)} mm",
                no_fail and s["chamfer"] <= chamfer_limit)]
    for k in rel_keys:
        targets.append((f"median {k} <= {TARGET_REL:.0%}", _fmt(s[k], pct=True), no_fail and s[k] <= TARGET_REL))
    return targets


def summarize(case: str, jobs: list[dict]) -> dict:
    s = median_figures(jobs, tuple(k for k in REL_KEYS if case != "noforce" or k != "mass_rel"))
    targets = accuracy_targets(s, TARGET_CHAMFER[case], REL_KEYS if case == "box" else ())
    targets.append(("median wall time <= recording duration", f"x{_fmt(s['realtime_ratio'], digits=2)}",
                    s["failures"] == 0 and s["realtime_ratio"] <= TARGET_REALTIME))
    s["targets"] = [{"target": t, "value": v, "met": bool(m)} for t, v, m in targets]
    return s


def _fmt(v, scale=1.0, digits=1, pct=False):
    if v is None or not np.isfinite(v):
        return "-"
    return f"{100 * v:.{digits}f} %" if pct else f"{v * scale:.{digits}f}"


def print_table(results: dict):
    head = (f"{'case':9s} {'method':9s} {'runs':>4s} {'fail':>4s} {'chamfer mm':>10s} {'mass':>8s} "
            f"{'mu_gnd':>8s} {'mu_fgr':>8s} {'wall s':>7s} {'rec s':>6s} {'wall/rec':>8s}")
    print(head)
    print("-" * len(head))
    for case, per_method in results.items():
        for method, res in per_method.items():
            s = res["summary"]
            print(f"{case:9s} {method:9s} {s['runs']:4d} {s['failures']:4d} {_fmt(s['chamfer'], 1e3, 2):>10s} "
                  f"{_fmt(s['mass_rel'], pct=True):>8s} {_fmt(s['friction_ground_rel'], pct=True):>8s} "
                  f"{_fmt(s['friction_finger_rel'], pct=True):>8s} {_fmt(s['wall']):>7s} "
                  f"{_fmt(s['duration']):>6s} {_fmt(s['realtime_ratio'], digits=2):>8s}")
    print()
    print("targets (medians over successful runs, wall time over all; any failure fails the target):")
    for case, per_method in results.items():
        for method, res in per_method.items():
            s = res["summary"]
            for t in s["targets"]:
                print(f"  {case:9s} {method:9s} {'PASS' if t['met'] else 'FAIL'}  {t['target']:42s} "
                      f"(measured {t['value']})")
            if s["failures"]:
                print(f"  {case:9s} {method:9s} failures: {s['failures']} of {s['runs']} "
                      f"({'; '.join(s['failure_reasons'])})")
    if "noforce" in results:
        print("  (no-force boxes: the mass is not identifiable without a force stream and is not scored)")


def print_scaling(scaling: dict):
    print()
    print("speed scaling (one box recording cut to T samples; wall time and its ratio to T=200;")
    print("target: no worse than linear, i.e. ratio / (T / 200) <= 1; s/iteration of successful solves below)")
    print(f"{'method':9s} " + " ".join(f"{'T=' + str(T):>12s}" for T in SCALING_T) + f" {'worst ratio/linear':>19s}")
    for method, jobs in scaling.items():
        base = jobs[0]["wall"] if jobs and np.isfinite(jobs[0]["wall"]) else math.nan
        cells, worst = [], 0.0
        for T, j in zip(SCALING_T, jobs):
            ratio = j["wall"] / base if np.isfinite(base) else math.nan
            mark = "" if j.get("ok") else "!"
            cells.append(f"{j['wall']:6.1f}s x{ratio:4.1f}{mark}" if np.isfinite(j["wall"]) else "-")
            if np.isfinite(ratio):
                worst = max(worst, ratio / (T / SCALING_T[0]))
        failed = [f"T={T}: {j['status']}" for T, j in zip(SCALING_T, jobs) if not j.get("ok")]
        verdict = "PASS" if worst <= 1.0 and not failed else "FAIL"
        print(f"{method:9s} " + " ".join(f"{c:>12s}" for c in cells) + f" {worst:12.2f} {verdict}")
        per_it = [f"{j['wall'] / j['iterations']:.3f}" if j.get("ok") and j.get("iterations") else "-"
                  for j in jobs]
        print(f"{'  s/iter':9s} " + " ".join(f"{c:>12s}" for c in per_it))
        if failed:
            print(f"          failed (!, time still shown): {'; '.join(failed)}")


# ------------------------------------------------------------------------------------


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=10, help="seeds 0..N-1 (default 10)")
    p.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of " + ",".join(CASES))
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of " + ",".join(METHODS))
    p.add_argument("--timeout", type=float, default=600.0, help="s per estimate (default 600)")
    p.add_argument("--json", dest="json_out", default=None, help="also write all figures to this JSON file")
    p.add_argument("--quiet", action="store_true", help="only the tables")
    p.add_argument("--reach", type=float, default=None, metavar="M",
                   help="noise.complementarity_reach of the estimates (m; 0: off; default: the estimator's default)")
    p.add_argument("--worker", nargs=4, metavar=("RUN", "SHAPE", "METHOD", "REACH"), help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.worker:
        print(json.dumps(worker(*a.worker)))
        return 0
    cases = [c for c in a.cases.split(",") if c]
    methods = [m for m in a.methods.split(",") if m]
    bad = [c for c in cases if c not in CASES] + [m for m in methods if m not in METHODS]
    if bad or a.seeds < 1:
        p.error(f"unknown case or method: {', '.join(bad)}" if bad else "--seeds must be >= 1")
    if a.reach is not None and not a.reach >= 0:
        p.error(f"--reach must be >= 0 (m), got {a.reach}")

    def say(msg):
        if not a.quiet:
            print(msg, file=sys.stderr, flush=True)

    say(f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} (other work slows the wall clock)")
    results, scaling = {}, {}
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_estimate_") as tmp:
        tmp = Path(tmp)
        for case in [c for c in cases if c != "scaling"]:
            results[case] = {m: {"jobs": []} for m in methods}
            for seed in range(a.seeds):
                path, shape = record(case, seed, tmp)
                for m in methods:
                    j = run_job(path, shape, m, a.timeout, a.reach)
                    j.update(seed=seed, shape=shape)
                    results[case][m]["jobs"].append(j)
                    if j.get("ok"):
                        say(f"[{case} seed {seed} {m}] {j['status']}: chamfer {1e3 * j['chamfer']:.2f} mm, "
                            f"wall {j['wall']:.1f} s for {j['duration']:.1f} s recorded")
                    else:
                        say(f"[{case} seed {seed} {m}] FAILED ({j['status']}): {j['error']} "
                            f"[{j['wall']:.1f} s]")
            for m in methods:
                results[case][m]["summary"] = summarize(case, results[case][m]["jobs"])
        if "scaling" in cases:
            cuts = record_scaling(tmp)
            for m in methods:
                scaling[m] = []
                for T, path in cuts:
                    j = run_job(path, "box", m, a.timeout, a.reach)
                    j["T"] = T
                    scaling[m].append(j)
                    say(f"[scaling T={T} {m}] {j['status'] or 'failed'}: wall {j['wall']:.1f} s")
    say(f"benchmark took {time.perf_counter() - t_all:.0f} s")
    if results:
        print_table(results)
    if scaling:
        print_scaling(scaling)
    if a.json_out:
        doc = {"seeds": a.seeds, "timeout": a.timeout, "reach": a.reach, "cases": results, "scaling": scaling}
        from tacest.evaluation.metrics import to_jsonable

        Path(a.json_out).write_text(json.dumps(to_jsonable(doc), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

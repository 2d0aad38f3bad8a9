"""Benchmark active exploration: closed loops (``tacest explore``) with EIG vs random pokes.

    nice -n 5 .venv/bin/python benchmarks/bench_plan.py [--seeds 10] [--cases box,polygon]
        [--policies eig,random] [--pokes 8] [--cache DIR (default /tmp/tacest_bench_plan)] [--timeout 7200] [--report-only]
        [--plot OUT.png] [--json OUT.json] [--quiet] [--retime N]

For every case, seed and policy it runs one closed loop in the pymunk world
(tacest.planning.explore.explore, 2-D, tacest record's default sensor noise):

- ``box``: a random box per seed, estimated as ``box``;
- ``polygon``: a random convex polygon of 5-7 vertices (``polygon:{5 + seed % 3}``),
  estimated as ``polygon:8`` (as benchmarks/bench_estimate.py).

The first poke of a seed is the same for every policy (the simulator's random poke);
the following ones are chosen by the policy.  After every poke the run is estimated and
scored against the truth (Chamfer of the placed shapes, parameter errors).

Resumable and parallel-safe: each loop is one job, run in its own subprocess (this script
with ``--worker``) under a time limit; its result (the explore summary, or the failure)
goes to ``<cache>/code_<digest>/<case>-<seed>-<policy>.json`` (written atomically; the digest
is tacest.provenance.source_digest of tacest's sources and this script, so that a table is
one code version's), and a job whose
result exists is not run again.  A job is claimed by creating ``<name>.lock`` exclusively,
so several copies of this script can share one cache and split the jobs; a lock whose
process is gone is taken over.  ``--report-only`` prints what the cache holds.

Printed: per case, over the paired seeds (those whose loops finished for every policy),
for n = 1 .. pokes and each policy: the median Chamfer distance (mm) with a failed
estimate ranked last (it has no Chamfer; the median reads ``fail`` when half or more
failed), the median over the successful estimates only, the number of failed estimates,
and the median mass and ground-friction errors of the successful ones; then the targets
with PASS / FAIL on the first median (two medians that both read ``fail`` count as
equal, and the line says so; a target against a ``fail`` median is UNDETERMINED):

1. EIG's median Chamfer after n pokes <= random's, for every n;
2. EIG reaches random's median Chamfer after ``pokes`` pokes within 4 pokes;
3. planning one poke (CEM included) takes <= 10 s (median and maximum over every EIG
   plan of the loops).

``--retime N``: after the report, plan again (EIG, the loops' settings) from the
estimates the cached EIG loops of the first N seeds wrote after pokes 1 .. pokes-1, one
plan at a time in this process, and print the median and maximum wall time: the
loops' own plan times depend on how many loops share the machine, these on the machine
alone (run it with nothing else running).

Exit status 0 whether or not the targets are met (1 only for bad arguments).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

CASES = ("box", "polygon")
POLICIES = ("eig", "random", "identity")
#: the issue's targets
TARGET_REACH_POKES = 4
TARGET_PLAN_TIME = 10.0  # s


def case_object(case: str, seed: int) -> tuple:
    """(object spec, estimator shape) of a case and seed."""
    if case == "box":
        return "box", "box"
    return f"polygon:{5 + seed % 3}", "polygon:8"


# ------------------------------------------------------------------------------------
# worker: one closed loop in its own process


def worker(case: str, seed: int, policy: str, pokes: int, out_dir: str) -> dict:
    from tacest.planning.explore import ExploreOptions, explore

    import logging

    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)  # the loop's progress lines
    obj, shape = case_object(case, seed)
    t0 = time.perf_counter()
    summary = explore(ExploreOptions(object_spec=obj, seed=seed, policy=policy, pokes=pokes, shape=shape), out_dir)
    return {"ok": True, "case": case, "seed": seed, "policy": policy, "wall": time.perf_counter() - t0,
            "summary": summary}


def _write_json(path: Path, obj) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
    tmp.write_text(json.dumps(obj, allow_nan=False) + "\n")
    os.replace(tmp, path)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def claim(lock: Path) -> bool:
    """Create ``lock`` exclusively (holding this pid); take over a lock whose process is gone."""
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().split()[0])
            except (OSError, ValueError, IndexError):
                return False  # being written right now: someone else's
            if _pid_alive(pid):
                return False
            lock.unlink(missing_ok=True)  # stale: its process died
            continue
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()} {time.time():.0f}\n")
        return True
    return False


def run_job(case, seed, policy, pokes, cache: Path, timeout: float, quiet: bool) -> dict | None:
    name = f"{case}-{seed}-{policy}"
    result_path = cache / f"{name}.json"
    if result_path.exists():
        return json.loads(result_path.read_text())
    lock = cache / f"{name}.lock"
    if not claim(lock):
        return None
    try:
        if result_path.exists():  # finished by another copy between our checks
            return json.loads(result_path.read_text())
        out_dir = cache / name
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", case, str(seed), policy, str(pokes),
               str(out_dir)]
        t0 = time.perf_counter()
        if not quiet:
            print(f"{name}: running ...", file=sys.stderr, flush=True)
        try:
            proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=None if not quiet else subprocess.DEVNULL,
                                  text=True, timeout=timeout)
            lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
            if proc.returncode != 0 or not lines:
                res = {"ok": False, "case": case, "seed": seed, "policy": policy,
                       "error": f"worker exit {proc.returncode}", "wall": time.perf_counter() - t0}
            else:
                res = json.loads(lines[-1])
        except subprocess.TimeoutExpired:
            res = {"ok": False, "case": case, "seed": seed, "policy": policy,
                   "error": f"no result within {timeout:.0f} s", "wall": time.perf_counter() - t0}
        res["pokes"] = pokes
        _write_json(result_path, res)
        if not quiet:
            print(f"{name}: {'done' if res['ok'] else 'FAILED: ' + res['error']} ({res['wall']:.0f} s)",
                  file=sys.stderr, flush=True)
        return res
    finally:
        lock.unlink(missing_ok=True)


# ------------------------------------------------------------------------------------
# report


def _nanmedian(a):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(np.nanmedian(a)) if len(a) else math.nan


def curves(results: list, pokes: int) -> dict:
    """{metric: (n_seeds, pokes) array}: +inf where the estimate failed (no estimate is
    worse than any estimate: it ranks last in the median), NaN where a value is missing
    (left out), and ``failed`` (n_seeds, pokes) bool."""
    keys = ("chamfer", "mass_rel", "friction_ground_rel", "friction_finger_rel")
    out = {k: np.full((len(results), pokes), np.nan) for k in keys}
    out["failed"] = np.zeros((len(results), pokes), bool)
    for i, r in enumerate(results):
        for st in r["summary"]["steps"]:
            n = st["pokes"]
            if n > pokes:
                continue
            failed = st.get("estimate_status") == "failed"
            for k in keys:
                v = st.get(k)
                out[k][i, n - 1] = math.inf if failed else (math.nan if v is None else v)
            out["failed"][i, n - 1] = failed
    return out


def _json_num(v):
    """A median for strict JSON: the number, "fail" for +inf, null for NaN."""
    return "fail" if math.isinf(v) else (None if math.isnan(v) else float(v))


def _fmt(v, width, digits):
    """A table cell: the number, 'fail' for +inf (half or more of the estimates failed),
    'n/a' for NaN."""
    if math.isinf(v):
        return f"{'fail':>{width}}"
    if math.isnan(v):
        return f"{'n/a':>{width}}"
    return f"{v:{width}.{digits}f}"


def report(all_results: dict, cases, policies, pokes: int, seeds) -> dict:
    """Print the tables and targets (module docstring) over the seeds for which every
    policy's loop finished (paired seeds); return them as a dict."""
    summary = {}
    lines = []
    for case in cases:
        done = {pol: {s for s in seeds if (all_results.get((case, s, pol)) or {}).get("ok")} for pol in policies}
        paired = sorted(set.intersection(*done.values())) if done else []
        lines.append(f"\n== {case}: {len(paired)} paired seeds {paired} ==")
        lines.append("per policy and n: median Chamfer (mm) with a failed estimate ranked last ('fail': half or "
                     "more failed) | median over the successful estimates only | failed estimates | median mass "
                     "and ground-friction errors (%) of the successful ones")
        cv, plan_times, failed_jobs = {}, {}, {}
        for pol in policies:
            res = [all_results[(case, s, pol)] for s in paired]
            failed_jobs[pol] = [f"{case}-{s}-{pol}: {all_results[(case, s, pol)]['error']}" for s in seeds
                                if (case, s, pol) in all_results and not all_results[(case, s, pol)].get("ok")]
            cv[pol] = curves(res, pokes)
            plan_times[pol] = [st["plan_time"] for r in res for st in r["summary"]["steps"] if "plan_time" in st]
        lines.append("pokes " + "".join(f"| {pol:>34} " for pol in policies))
        lines.append("      " + "".join(f"| {'ranked  success  fail  mass  mu_g':>34} " for _ in policies))
        med, med_ok = {pol: [] for pol in policies}, {pol: [] for pol in policies}
        for n in range(1, pokes + 1):
            row = f"{n:5d} "
            for pol in policies:
                c = cv[pol]
                col = c["chamfer"][:, n - 1]
                ch = _nanmedian(col) if paired else math.nan
                ch_ok = _nanmedian(col[np.isfinite(col)]) if paired else math.nan
                med[pol].append(ch)
                med_ok[pol].append(ch_ok)
                nf = int(c["failed"][:, n - 1].sum())
                mr, fr = (_nanmedian(c[k][:, n - 1][np.isfinite(c[k][:, n - 1])]) if paired else math.nan
                          for k in ("mass_rel", "friction_ground_rel"))
                row += (f"| {_fmt(1e3 * ch, 7, 2)} {_fmt(1e3 * ch_ok, 8, 2)} {nf:4d}/{len(paired):<2d}"
                        f"{_fmt(100 * mr, 5, 0)} {_fmt(100 * fr, 5, 0)} ")
            lines.append(row)
        for pol in policies:
            pt = plan_times[pol]
            if pt:
                lines.append(f"plan time {pol}: median {np.median(pt):.1f} s, max {np.max(pt):.1f} s "
                             f"over {len(pt)} plans")
            for f in failed_jobs[pol]:
                lines.append(f"FAILED loop {f}")
        entry = {"paired_seeds": paired,
                 "medians_chamfer_failures_last": {p: [_json_num(v) for v in med[p]] for p in policies},
                 "medians_chamfer_successes": {p: [_json_num(v) for v in med_ok[p]] for p in policies},
                 "failed_estimates": {p: cv[p]["failed"].sum(0).astype(int).tolist() for p in policies},
                 "plan_time": {p: {"median": float(np.median(v)) if v else None, "max": float(np.max(v)) if v else None,
                                   "count": len(v)} for p, v in plan_times.items()},
                 "failed_loops": failed_jobs}
        if "eig" in policies and "random" in policies and paired:
            e, r = np.array(med["eig"]), np.array(med["random"])
            every = bool(np.all(e <= r))
            worse = [n + 1 for n in range(pokes) if not e[n] <= r[n]]
            both_fail = [n + 1 for n in range(pokes) if math.isinf(e[n]) and math.isinf(r[n])]
            reach = next((n + 1 for n in range(pokes) if e[n] <= r[-1]), None)
            lines.append(f"target: EIG median chamfer <= random's at every n: {'PASS' if every else 'FAIL'}"
                         + ("" if every else f" (worse at n = {worse})")
                         + (f" (both medians 'fail' at n = {both_fail})" if both_fail else ""))
            if math.isinf(r[-1]) or math.isnan(r[-1]):
                reach = None
                lines.append(f"target: EIG reaches random's {pokes}-poke median within {TARGET_REACH_POKES} pokes: "
                             f"UNDETERMINED (random's {pokes}-poke median is {_fmt(r[-1], 1, 0).strip()})")
            else:
                ok = reach is not None and reach <= TARGET_REACH_POKES
                lines.append(f"target: EIG reaches random's {pokes}-poke median ({1e3 * r[-1]:.2f} mm) within "
                             f"{TARGET_REACH_POKES} pokes: {'PASS' if ok else 'FAIL'}"
                             f" (EIG reaches it after {reach if reach else 'more than ' + str(pokes)} pokes)")
            pt = plan_times["eig"]
            if pt:
                lines.append(f"target: planning one poke <= {TARGET_PLAN_TIME:.0f} s: "
                             f"{'PASS' if max(pt) <= TARGET_PLAN_TIME else 'FAIL'} (max {max(pt):.1f} s)")
            entry.update(every_n=every, reach_pokes=reach)
        summary[case] = entry
    print("\n".join(lines))
    return summary


def loop_estimates(folder: Path, last: int):
    """(n, estimate, the loop's run cut to the estimate's samples) for every
    ``estimate_<n>.h5`` of a loop folder, n = 1 .. last, that exists (none without run.h5)."""
    from tacest.io.slicing import slice_run
    from tacest.io.estimate import read_estimate
    from tacest.io.run import read_run

    if not (folder / "run.h5").exists():
        return
    run = read_run(folder / "run.h5")
    for n in range(1, last + 1):
        path = folder / f"estimate_{n}.h5"
        if path.exists():
            est = read_estimate(path)
            yield n, est, slice_run(run, 0, len(est.runs[0].pose))


def retime(cache: Path, cases, seeds, pokes: int) -> dict:
    """Wall times (s) of EIG plans from the cached EIG loops' estimates, one at a time:
    {case: [seconds, ...]} (see --retime)."""
    from tacest.planning.explore import plan_seed
    from tacest.planning.planner import PlanSettings, plan_next

    out = {}
    for case in cases:
        times = []
        for seed in seeds:
            for n, est, piece in loop_estimates(cache / f"{case}-{seed}-eig", pokes - 1):
                t0 = time.perf_counter()
                plan_next(est, [piece], PlanSettings(method="eig", seed=plan_seed(seed, n)))
                times.append(time.perf_counter() - t0)
        out[case] = times
        if times:
            print(f"{case}: EIG planning, one plan at a time: median {np.median(times):.2f} s, max "
                  f"{np.max(times):.2f} s over {len(times)} plans (load average now {os.getloadavg()[0]:.2f})")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--cases", default="box,polygon")
    ap.add_argument("--policies", default="eig,random")
    ap.add_argument("--pokes", type=int, default=8)
    ap.add_argument("--cache", default="/tmp/tacest_bench_plan")
    ap.add_argument("--timeout", type=float, default=7200.0)
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--plot", default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--quiet", action="store_true")
    ap.add_argument("--retime", type=int, default=0, metavar="N")
    ap.add_argument("--worker", nargs=5, metavar=("CASE", "SEED", "POLICY", "POKES", "DIR"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        case, seed, policy, pokes, out_dir = args.worker
        print(json.dumps(worker(case, int(seed), policy, int(pokes), out_dir), allow_nan=False))
        return 0
    cases = [c for c in args.cases.split(",") if c]
    policies = [p for p in args.policies.split(",") if p]
    if any(c not in CASES for c in cases) or any(p not in POLICIES for p in policies) or args.seeds < 1 \
            or args.pokes < 1:
        ap.error(f"cases from {CASES}, policies from {POLICIES}, seeds and pokes >= 1")
    # results of one code version only (tacest's sources and this script:
    # tacest.provenance.source_digest): a changed planner never reprints old figures
    from tacest.provenance import source_digest

    cache = Path(args.cache) / f"code_{source_digest(Path(__file__).resolve())}"
    cache.mkdir(parents=True, exist_ok=True)
    # a terminated benchmark kills its running worker and frees the job's lock
    signal.signal(signal.SIGTERM, lambda *a: sys.exit(143))
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}; "
          f"cache {cache}", file=sys.stderr)
    results = {}
    for seed in seeds:  # seed by seed, so that a partial benchmark compares like with like
        for case in cases:
            for pol in policies:
                name = cache / f"{case}-{seed}-{pol}.json"
                if args.report_only:
                    res = json.loads(name.read_text()) if name.exists() else None
                else:
                    res = run_job(case, seed, pol, args.pokes, cache, args.timeout, args.quiet)
                if res is not None and res.get("pokes", args.pokes) == args.pokes:
                    results[(case, seed, pol)] = res
    summary = report(results, cases, policies, args.pokes, seeds)
    if args.plot:
        from tacest.planning.explore import plot_learning_curve

        for case in cases:
            sums = [r["summary"] for (c, s, p), r in results.items() if c == case and r.get("ok")]
            if sums:
                out = Path(args.plot)
                plot_learning_curve(out.with_name(f"{out.stem}_{case}{out.suffix}"), sums)
    retimed = retime(cache, cases, seeds[: args.retime], args.pokes) if args.retime > 0 else {}
    if args.json:
        Path(args.json).write_text(json.dumps({"cases": summary, "seeds": seeds, "pokes": args.pokes,
                                               "results": {"-".join(map(str, k)): v for k, v in results.items()},
                                               "retimed_plan_times": retimed},
                                              indent=1, default=lambda o: None) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

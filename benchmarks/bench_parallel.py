"""Benchmark the executor (tacest.parallel): one diagnosis of the toss design of
bench_diagnose.py (one seed, every SPEC candidate) in this process (``--workers 1``)
and on a local Dask cluster of ``--workers N`` processes (default 2).

    nice -n 10 .venv/bin/python benchmarks/bench_parallel.py [--effect none] [--seed 0] [--workers 2]
                                                             [--cache DIR] [--json OUT.json]

Printed: the load average before and after each diagnosis (another process on the
machine slows either), the wall time of each (cluster start and stop included), their
ratio (target: at most 0.6 with 2 workers), whether the verdict and every figure of the
JSON report (wall times left out) are equal, and the figures docs/parallel.md scales
from: the tasks and their compute times (in this process), the bytes of the scattered
context (run data and settings) and of a fit sent between tasks, and each worker's peak
resident memory.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import statistics
import sys
import tempfile
import time
from pathlib import Path


TARGET_RATIO = 0.6


def _strip(obj):
    """The report without what may differ between two equal diagnoses (times, the
    command line)."""
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in ("wall_time", "command_line")}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _peak_rss_mb(dask_worker=None) -> float:
    """Peak resident memory of this process, MB: VmHWM of /proc/self/status (reset at
    exec, unlike getrusage's ru_maxrss, which a spawned worker inherits from the process
    that started it), else ru_maxrss."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_once(runs, workers: int, cold_starts: str = None) -> dict:
    """One diagnosis with ``workers`` (1: in this process) and ``cold_starts``
    (DiagnoseOptions.cold_starts; None: its default): wall time, report, tasks."""
    from tacest.diagnosis.diagnose import DiagnoseOptions, diagnose
    from tacest.parallel import Executor, ParallelSettings

    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    with Executor(ParallelSettings(workers=workers)) as ex:
        opts = DiagnoseOptions() if cold_starts is None else DiagnoseOptions(cold_starts=cold_starts)
        d = diagnose(runs, "box", options=opts, executor=ex)
        memory = ex._client.run(_peak_rss_mb) if ex._client is not None else {"in-process": _peak_rss_mb()}
        per_worker = ex.tasks_per_worker()  # the scheduler's task stream, before the cluster stops
    wall = time.perf_counter() - t0
    return {"workers": workers, "wall": wall, "load_before": load0, "load_after": os.getloadavg()[0],
            "verdict": d.verdict, "report": d.to_json(), "tasks": [[k, w, s] for k, w, s in ex.task_log],
            "per_worker": per_worker, "peak_rss_mb": memory, "diagnosis": d}


def sizes(runs, diag) -> dict:
    """Bytes (pickled) of what the graph sends: the context (runs and settings), one run,
    and the plain fit (the largest result a task sends on)."""
    from tacest.diagnosis.diagnose import _Context, DiagnoseOptions
    from tacest.diagnosis.fitting import FitResult
    from tacest.estimation.config import EstimatorConfig

    ctx = _Context(runs, "box", EstimatorConfig(), DiagnoseOptions(), "warm")
    return {"context": len(pickle.dumps(ctx)), "run": len(pickle.dumps(runs[0])),
            "plain_fit": len(pickle.dumps(FitResult(estimate=diag.base, runs=[])))}


def task_table(tasks) -> dict:
    """{task kind: [count, median s, max s, sum s]} of a task log (kind: the key's name)."""
    out = {}
    for key, _, s in tasks:
        kind = key.split("-")[1] if key.count("-") >= 2 else key
        if "fold" in key:
            kind = "plain-fold" if key.startswith("tacest-plain-fold") else "candidate-fold"
        elif key.startswith("tacest-plain-fit"):
            kind = "plain-fit"
        elif any(key.endswith(x) or f"-{x}-" in key for x in ("cold", "warm", "typical")):
            kind = "start"
        elif "-fit-" in key:
            kind = "transform-fit"
        elif "-choose-" in key:
            kind = "choose"
        out.setdefault(kind, []).append(s)
    return {k: [len(v), statistics.median(v), max(v), sum(v)] for k, v in out.items()}


def main(argv=None) -> int:
    import bench_diagnose as bd  # the sibling script (this folder is on sys.path when a script runs)
    from tacest.diagnosis.diagnose import COLD_STARTS
    from tacest.io.run import read_run

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--effect", default="none", help="the effect hidden in the recording (default none)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2, help="local workers of the second run (default 2)")
    ap.add_argument("--cache", default=None, help="folder of the recording (default $TMPDIR/tacest_bench_diagnose)")
    ap.add_argument("--json", default=None, help="write the figures to this file")
    ap.add_argument("--cold-starts", default=None, choices=COLD_STARTS,
                    help="which candidates also start from the estimator's own starts (default: the diagnosis' "
                         "default, DiagnoseOptions.cold_starts)")
    a = ap.parse_args(argv)
    cache = Path(a.cache or Path(tempfile.gettempdir()) / "tacest_bench_diagnose")
    cache.mkdir(parents=True, exist_ok=True)
    rec = bd.record_toss_design(a.effect, a.seed, bd.TOSS_PAIRS, cache)
    runs = [read_run(p) for p in rec.bare]
    print(f"load average {os.getloadavg()[0]:.2f}; {os.cpu_count()} cores; recording {rec.bare[0].name} and "
          f"{len(rec.bare) - 1} more runs ({sum(r.n_samples for r in runs)} samples), effect {a.effect}, seed "
          f"{a.seed}; every candidate", flush=True)
    one = run_once(runs, 1, a.cold_starts)
    print(f"--workers 1: {one['wall']:.0f} s (load {one['load_before']:.2f} -> {one['load_after']:.2f}), "
          f"verdict {one['verdict']}", flush=True)
    many = run_once(runs, a.workers, a.cold_starts)
    print(f"--workers {a.workers}: {many['wall']:.0f} s (load {many['load_before']:.2f} -> "
          f"{many['load_after']:.2f}), verdict {many['verdict']}, tasks per worker "
          + ", ".join(f"{w} {n}" for w, n in sorted(many["per_worker"].items())), flush=True)
    ratio = many["wall"] / one["wall"]
    same = _strip(one["report"]) == _strip(many["report"])
    table = task_table(one["tasks"])
    size = sizes(runs, one["diagnosis"])
    print("\ntasks (compute time in this process): kind, count, median s, max s, total s")
    for k, (n, med, mx, tot) in sorted(table.items(), key=lambda t: -t[1][3]):
        print(f"  {k:<16} {n:>3} {med:>8.1f} {mx:>8.1f} {tot:>8.1f}")
    print(f"  all              {len(one['tasks']):>3} {'':>8} {'':>8} {sum(t[2] for t in one['tasks']):>8.1f}")
    print(f"bytes sent: context (runs and settings) {size['context']}, one run {size['run']}, "
          f"the plain fit {size['plain_fit']}")
    print("peak resident memory, MB: in this process " + ", ".join(f"{v:.0f}" for v in one["peak_rss_mb"].values())
          + "; workers " + ", ".join(f"{v:.0f}" for v in many["peak_rss_mb"].values()))
    print("\ntargets")
    print(f"  {'PASS' if ratio <= TARGET_RATIO else 'FAIL'}  wall time with {a.workers} workers <= "
          f"{TARGET_RATIO} x one process: {ratio:.2f}")
    print(f"  {'PASS' if one['verdict'] == many['verdict'] else 'FAIL'}  same verdict: {one['verdict']} / "
          f"{many['verdict']}")
    print(f"  {'PASS' if same else 'FAIL'}  every figure of the report equal (wall times left out)")
    if a.json:
        for r in (one, many):
            r.pop("diagnosis")
        Path(a.json).write_text(json.dumps({"one": one, "many": many, "ratio": ratio, "same": same,
                                            "tasks": table, "bytes": size}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())

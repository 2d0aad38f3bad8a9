"""Benchmark the 3-D estimator (``estimate_3d``) on simulated finger pokes of a box.

    .venv/bin/python benchmarks/bench_estimate3d.py [--seeds 10] [--first 0] [--pokes 6]
                                                    [--timeout 900] [--quiet] [--json OUT.json]

Case: ``tacest record --source sim --dim 3 --object box --pokes 6 --seed S`` (MuJoCo; a
random box per seed, one spherical fingertip, 100 Hz, about 9-11 s; fingertip position,
contact flag, normal and force, NO pose observations), estimated as ``box`` with the
default config (starts of tacest/estimation/initial3d.py, restarts of ``[solver3d]``).

Every estimate runs in its own subprocess (bench_estimate.py's worker, which hands a 3-D
run to ``estimate_3d``) with a time limit; a SolveFailedError, any other error and a
timeout count as failures and are reported with their reason.  Wall time is measured in
the worker around the estimate (NLP construction and every restart included; Python
start-up and imports not).

Printed per seed: Chamfer distance (mm, the placed shapes over time, as ``tacest eval``),
relative errors of mass and of ground and finger friction, wall time, recording duration,
and the starts tried (label, objective, physics terms per sample).  Then the medians over
the successful runs, the failures, and the targets with PASS / FAIL (as the 2-D box case
of bench_estimate.py): median Chamfer <= 3 mm, median mass and friction errors <= 15 %;
a target counts as met only if no run failed.  Wall time / recording duration is printed,
not targeted (3-D restarts solve up to 1 + solver3d.restarts NLPs).
The exit status is 0 whether or not the targets are met (1 only for bad arguments).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

# the sibling script (this folder is on sys.path when a benchmark script runs)
from bench_estimate import TARGET_CHAMFER, _fmt, accuracy_targets, median_figures, run_job


def record(seed: int, pokes: int, directory: Path) -> Path:
    """Record the 3-D poke run of ``seed`` (as ``tacest record --source sim --dim 3
    --object box --pokes N --seed S``)."""
    from tacest.io.run import write_run
    from tacest.dims import record_sim
    from tacest.sim.record import SimOptions

    path = directory / f"pokes3d_{seed}.h5"
    write_run(record_sim(SimOptions(dim=3, object_spec="box", pokes=pokes, seed=seed)), path)
    return path


def _starts(j) -> str:
    parts = []
    for a in j.get("starts", []):
        if a.get("status") in ("failed", "abandoned"):
            parts.append(f"{a['start']}: {a['status']}")
        else:
            parts.append(f"{a['start']}: obj {a['objective']:.0f}, phys {a['physics_per_sample']:.3f}")
    return "; ".join(parts)


def summarize(jobs: list[dict]) -> dict:
    s = median_figures(jobs)
    s["targets"] = [{"target": t, "value": v, "met": bool(m)}
                    for t, v, m in accuracy_targets(s, TARGET_CHAMFER[("box", "gentle")])]
    return s


def print_results(jobs: list[dict], s: dict):
    head = (f"{'seed':>4s} {'chamfer mm':>10s} {'mass':>8s} {'mu_gnd':>8s} {'mu_fgr':>8s} {'wall s':>7s} "
            f"{'rec s':>6s}  starts (objective, physics terms per sample)")
    print(head)
    print("-" * len(head))
    for j in jobs:
        if j.get("ok"):
            print(f"{j['seed']:4d} {_fmt(j.get('chamfer'), 1e3, 2):>10s} {_fmt(j.get('mass_rel'), pct=True):>8s} "
                  f"{_fmt(j.get('friction_ground_rel'), pct=True):>8s} "
                  f"{_fmt(j.get('friction_finger_rel'), pct=True):>8s} {_fmt(j['wall']):>7s} "
                  f"{_fmt(j.get('duration')):>6s}  {_starts(j)}")
        else:
            print(f"{j['seed']:4d} FAILED ({j['status']}): {j['error']} [{_fmt(j['wall'])} s]")
    print("-" * len(head))
    print(f"{'med':>4s} {_fmt(s['chamfer'], 1e3, 2):>10s} {_fmt(s['mass_rel'], pct=True):>8s} "
          f"{_fmt(s['friction_ground_rel'], pct=True):>8s} {_fmt(s['friction_finger_rel'], pct=True):>8s} "
          f"{_fmt(s['wall']):>7s} {_fmt(s['duration']):>6s}  wall/rec x{_fmt(s['realtime_ratio'], digits=2)}; "
          f"failures {s['failures']} of {s['runs']}")
    print()
    print("targets (medians over successful runs; any failure fails the target):")
    for t in s["targets"]:
        print(f"  {'PASS' if t['met'] else 'FAIL'}  {t['target']:36s} (measured {t['value']})")
    if s["failures"]:
        print(f"  failures: {s['failures']} of {s['runs']} ({'; '.join(s['failure_reasons'])})")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=10, help="number of seeds (default 10)")
    p.add_argument("--first", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--pokes", type=int, default=6, help="pokes per recording (default 6)")
    p.add_argument("--timeout", type=float, default=900.0, help="s per estimate (default 900)")
    p.add_argument("--json", dest="json_out", default=None, help="also write all figures to this JSON file")
    p.add_argument("--quiet", action="store_true", help="only the tables")
    a = p.parse_args(argv)
    if a.seeds < 1 or a.pokes < 1:
        p.error("--seeds and --pokes must be >= 1")

    def say(msg):
        if not a.quiet:
            print(msg, file=sys.stderr, flush=True)

    say(f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} (other work slows the wall clock)")
    jobs = []
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_estimate3d_") as tmp:
        for seed in range(a.first, a.first + a.seeds):
            j = run_job(record(seed, a.pokes, Path(tmp)), "box", "implicit", a.timeout)
            j["seed"] = seed
            jobs.append(j)
            if j.get("ok"):
                say(f"[pokes3d seed {seed}] {j['status']}: chamfer {1e3 * j['chamfer']:.2f} mm, "
                    f"wall {j['wall']:.1f} s for {j['duration']:.1f} s recorded; {_starts(j)}")
            else:
                say(f"[pokes3d seed {seed}] FAILED ({j['status']}): {j['error']} [{j['wall']:.1f} s]")
    say(f"benchmark took {time.perf_counter() - t_all:.0f} s; load average now {os.getloadavg()[0]:.2f}")
    s = summarize(jobs)
    print_results(jobs, s)
    if a.json_out:
        from tacest.evaluation.metrics import to_jsonable

        Path(a.json_out).write_text(json.dumps(to_jsonable({"seeds": list(range(a.first, a.first + a.seeds)),
                                                       "pokes": a.pokes, "jobs": jobs, "summary": s}), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

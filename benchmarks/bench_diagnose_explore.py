"""Benchmark the diagnosis' closed loop from touch alone (``tacest diagnose --explore``):
suggested pokes against random ones, side by side, on the same recordings.

    nice -n 10 .venv/bin/python benchmarks/bench_diagnose_explore.py [--effects none,linear_drag,...]
        [--candidates a,b,...] [--seeds 1] [--first-seed 0] [--pokes 4] [--budget 6]
        [--policies suggest,random] [--max-folds 3] [--fit-iterations 150]
        [--cache DIR] [--timeout 7200] [--workers N] [--json OUT.json]

For every effect and seed, a 2-D box is recorded by tacest's simulator with the effect
hidden (its seed's random strength; no pose observations, no weighed mass: touch alone)
and ``--pokes`` random pokes; each policy then runs the loop (tacest.diagnosis.explore)
in its own subprocess: diagnose, add a poke (suggested, or random from the same action
space), until the verdict names an effect or ``--budget`` pokes are added.  Both policies
start from the same recording (same seed).  ``--candidates`` restricts every diagnosis'
candidate set (default: every SPEC effect; a smaller set is faster and easier, say so
when quoting).  Results are cached per loop under ``<cache>/code_<digest>`` (digest of
tacest's sources and this script).

Printed per policy: top-1 (the final verdict is the hidden effect; ``none`` for clean
recordings), clean recordings blamed, median actions to the right verdict, the median gap
closed by the right effect at the end, and the median wall time of a loop.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def run_loop(effect, seed, policy, args, folder: Path) -> dict:
    cmd = [sys.executable, "-m", "tacest", "diagnose", "--explore", "--inject", effect, "--seed", str(seed),
           "--pokes", str(args.pokes), "--budget", str(args.budget), "--policy", policy,
           "--max-folds", str(args.max_folds), "--fit-iterations", str(args.fit_iterations),
           "-o", str(folder), "--json", "--quiet", "--workers", str(args.workers)]
    if args.candidates:
        cmd += ["--effects", args.candidates]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
    except subprocess.TimeoutExpired:
        return {"ok": False, "error": f"timeout after {args.timeout:.0f} s"}
    if out.returncode < 0:  # no line of its own: e.g. the kernel's out-of-memory kill (SIGKILL)
        return {"ok": False, "error": f"killed by signal {-out.returncode}"}
    if out.returncode != 0:  # the CLI's one error line (after any warnings)
        lines = [ln for ln in out.stderr.strip().splitlines() if not ln.startswith("warning:")]
        return {"ok": False, "error": f"exit {out.returncode}: {(lines or ['?'])[-1]}"}
    s = json.loads(out.stdout)
    steps = s["steps"]
    right = [st["actions"] for st in steps if st["verdict"] == effect]
    last = steps[-1]["candidates"].get(effect, {})
    return {"ok": True, "verdict": s["verdict"], "actions": steps[-1]["actions"],
            "actions_to_right": right[0] if right else None,
            # a right effect not held out (status screened: its fit to all data beat no penalty) closed nothing
            "right_reduction": 0.0 if last.get("status") == "screened" else last.get("reduction"),
            "wall": s.get("wall_time"), "steps": [{"actions": st["actions"], "verdict": st["verdict"]} for st in steps]}


def main(argv=None):
    from tacest.provenance import source_digest

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--effects", default="none,linear_drag,angular_damping,com_offset,restitution,force_bias")
    ap.add_argument("--candidates", default="")
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--pokes", type=int, default=4)
    ap.add_argument("--budget", type=int, default=6)
    ap.add_argument("--policies", default="suggest,random")
    ap.add_argument("--max-folds", type=int, default=3)
    ap.add_argument("--fit-iterations", type=int, default=150)
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "tacest_bench_diagnose_explore"))
    ap.add_argument("--timeout", type=float, default=7200.0)
    ap.add_argument("--workers", type=int, default=1,
                    help="worker processes of each diagnosis' local cluster (1: in the loop's process)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    effects = [e for e in args.effects.split(",") if e]
    policies = [p for p in args.policies.split(",") if p]
    tag = f"p{args.pokes}-b{args.budget}-f{args.max_folds}-i{args.fit_iterations}-c{args.candidates or 'all'}"
    if args.workers > 1:  # the same verdicts, other wall times
        tag += f"-w{args.workers}"
    cache = Path(args.cache) / f"code_{source_digest(Path(__file__).resolve())}" / tag
    cache.mkdir(parents=True, exist_ok=True)
    print(f"cache {cache}", flush=True)
    results = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for eff in effects:
            for pol in policies:
                path = cache / f"{eff}-{seed}-{pol}.json"
                if path.is_file():
                    r = json.loads(path.read_text())
                else:
                    r = run_loop(eff, seed, pol, args, cache / f"{eff}-{seed}-{pol}")
                    r.update(effect=eff, seed=seed, policy=pol)
                    path.write_text(json.dumps(r))
                results.append(r)
                print(f"{eff}-{seed} {pol}: " + (f"verdict {r['verdict']} after {r['actions']} actions "
                                                 f"({r['wall']:.0f} s)" if r["ok"] else f"FAILED {r['error']}"),
                      flush=True)
    summary = {}
    for pol in policies:
        rs = [r for r in results if r["policy"] == pol and r["ok"]]
        eff_rs = [r for r in rs if r["effect"] != "none"]
        clean = [r for r in rs if r["effect"] == "none"]
        reds = [r["right_reduction"] for r in eff_rs if r["right_reduction"] is not None]
        acts = [r["actions_to_right"] for r in eff_rs if r["actions_to_right"] is not None]
        summary[pol] = {
            "top1": f"{sum(r['verdict'] == r['effect'] for r in eff_rs) + sum(r['verdict'] == 'none' for r in clean)}"
                    f"/{len(rs)}",
            "top1_effects": f"{sum(r['verdict'] == r['effect'] for r in eff_rs)}/{len(eff_rs)}",
            "clean_blamed": f"{sum(r['verdict'] != 'none' for r in clean)}/{len(clean)}",
            "median_actions_to_right": float(np.median(acts)) if acts else None,
            "median_right_reduction": float(np.median(reds)) if reds else None,
            "median_wall_s": float(np.median([r["wall"] for r in rs])) if rs else None}
        print(pol, json.dumps(summary[pol]))
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "results": results}, indent=1))


if __name__ == "__main__":
    main()

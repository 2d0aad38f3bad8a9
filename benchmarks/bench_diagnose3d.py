"""Benchmark the 3-D diagnosis (``tacest diagnose`` on 3-D pose-observed runs) on MuJoCo
recordings whose effect is hidden from it.

    nice -n 10 .venv/bin/python benchmarks/bench_diagnose3d.py [--effects none,com_offset,...]
        [--seeds 3] [--first-seed 0] [--pokes 6] [--poke-style dynamic|gentle|mixed]
        [--cache DIR] [--timeout 1800] [--json OUT.json] [--quiet]

For every effect (default: ``none`` and every SPEC effect the 3-D model has,
tacest.diagnosis.diagnose3d.SPEC_EFFECTS_3D) and seeds FIRST..FIRST+N-1 it records one
3-D run of a box in the MuJoCo world (``--pokes`` pokes of ``--poke-style`` by one
force-sensing finger, the effect at the strength its seed draws, docs/effects.md; the
pose observed at 0.5 mm as by motion capture), cuts it at its pokes into sub-runs
(tacest.diagnosis.slicing.split_at_actions), and diagnoses them without the truth: the
first half trains, the second is held out.  Each diagnosis runs in its own subprocess
(this script with ``--worker``) under a time limit.  Results are cached per recording in
``<cache>/code_<digest>/<effect>-<seed>.json`` (digest: tacest.provenance.source_digest of
tacest's sources and this script: a changed diagnosis never reprints old figures).

Printed: per effect the verdicts and the right effect's reduction; then top-1 over the
effects, over effects and clean recordings, clean recordings blamed, the median held-out
gap closed by the right effect, and the median wall time of a diagnosis.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: m, sigma of the observed positions (motion capture); angles 0.5 mm / 5 cm
OBSERVE_POSE = 0.0005


def worker(effect: str, seed: int, pokes: int, style: str) -> dict:
    """Record, cut and diagnose one recording (in this process); a JSON-able dict."""
    from tacest.diagnosis.diagnose3d import diagnose_3d
    from tacest.diagnosis.slicing import split_at_actions
    from tacest.dims import record_sim
    from tacest.sim.record import SimOptions

    opts = SimOptions(dim=3, seed=seed, pokes=pokes, fingers=1, effects=[] if effect == "none" else [effect],
                      observe_pose=OBSERVE_POSE, poke_style=style)
    run = record_sim(opts)
    truth = run.truth.effects
    parts = [p.replace(filename=f"part{i}", truth=None) for i, p in enumerate(split_at_actions(run))]
    t0 = time.perf_counter()
    d = diagnose_3d(parts, "box")
    wall = time.perf_counter() - t0
    right = next((e for e in d.effects if e["name"] == effect), None)
    return {"ok": True, "effect": effect, "seed": seed, "truth": truth, "verdict": d.verdict, "wall": wall,
            "right_reduction": None if right is None else right["reduction"],
            "effects": [{k: e[k] for k in ("name", "reduction", "gap_before", "gap_after", "params")}
                        for e in d.effects], "parts": len(parts), "reason": d.reason}


def run_job(effect, seed, pokes, style, timeout) -> dict:
    cmd = [sys.executable, __file__, "--worker", effect, str(seed), str(pokes), style]
    t0 = time.perf_counter()
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"ok": False, "effect": effect, "seed": seed, "error": f"timeout after {timeout:.0f} s"}
    if out.returncode != 0:
        tail = (out.stderr.strip().splitlines() or ["?"])[-1]
        return {"ok": False, "effect": effect, "seed": seed, "error": tail, "wall": time.perf_counter() - t0}
    return json.loads(out.stdout.strip().splitlines()[-1])


def report(results: list, effects: list) -> dict:
    ok = [r for r in results if r.get("ok")]
    rows = []
    for eff in effects:
        rs = [r for r in ok if r["effect"] == eff]
        verdicts = ", ".join(f"{r['seed']}:{r['verdict']}" for r in rs)
        reds = [r["right_reduction"] for r in rs if r["right_reduction"] is not None]
        right = sum(r["verdict"] == eff for r in rs)
        red = f"{np.median(reds):.0%}" if reds else "-"
        rows.append(f"| {eff} | {right}/{len(rs)} | {red} | {verdicts} |")
    eff_rs = [r for r in ok if r["effect"] != "none"]
    clean = [r for r in ok if r["effect"] == "none"]
    top1_eff = sum(r["verdict"] == r["effect"] for r in eff_rs)
    top1_all = top1_eff + sum(r["verdict"] == "none" for r in clean)
    reds = [r["right_reduction"] for r in eff_rs if r["right_reduction"] is not None]
    walls = [r["wall"] for r in ok]
    summary = {"top1_effects": f"{top1_eff}/{len(eff_rs)}", "top1_all": f"{top1_all}/{len(ok)}",
               "clean_blamed": f"{sum(r['verdict'] != 'none' for r in clean)}/{len(clean)}",
               "median_right_reduction": float(np.median(reds)) if reds else None,
               "median_wall_s": float(np.median(walls)) if walls else None,
               "failed": [f"{r['effect']}-{r['seed']}: {r.get('error')}" for r in results if not r.get("ok")]}
    print("| effect | right | median gap closed by it | verdicts (seed:verdict) |")
    print("|---|---|---|---|")
    print("\n".join(rows))
    for k, v in summary.items():
        print(f"{k}: {v}")
    return summary


def main(argv=None):
    from tacest.diagnosis.diagnose3d import SPEC_EFFECTS_3D
    from tacest.provenance import source_digest

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--effects", default=",".join(("none",) + SPEC_EFFECTS_3D))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--pokes", type=int, default=6)
    ap.add_argument("--poke-style", default="dynamic")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "tacest_bench_diagnose3d"))
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--json", default=None)
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    cache = Path(args.cache) / f"code_{source_digest(Path(__file__).resolve())}"
    cache.mkdir(parents=True, exist_ok=True)
    print(f"cache {cache}; {args.pokes} {args.poke_style} pokes, seeds {args.first_seed}.."
          f"{args.first_seed + args.seeds - 1}", flush=True)
    results = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for eff in effects:
            path = cache / f"{eff}-{seed}-{args.pokes}-{args.poke_style}.json"
            if path.is_file():
                r = json.loads(path.read_text())
            else:
                r = run_job(eff, seed, args.pokes, args.poke_style, args.timeout)
                tmp = path.with_suffix(".tmp")
                tmp.write_text(json.dumps(r))
                tmp.replace(path)
            results.append(r)
            if not args.quiet:
                print(f"{eff}-{seed}: " + (f"verdict {r['verdict']} ({r['wall']:.0f} s)" if r.get("ok")
                                          else f"FAILED {r.get('error')}"), flush=True)
    summary = report(results, effects)
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summary, "results": results}, indent=1))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        import logging

        logging.basicConfig(level=logging.WARNING)
        print(json.dumps(worker(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5])))
    else:
        main()

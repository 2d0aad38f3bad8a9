"""Benchmark the 3-D diagnosis (``tacest diagnose`` on 3-D pose-observed runs) on MuJoCo
recordings whose effect is hidden from it.

    nice -n 10 .venv/bin/python benchmarks/bench_diagnose3d.py [--effects none,com_offset,...]
        [--design toss|pokes] [--seeds 3] [--first-seed 0] [--runs 4] [--pokes 6]
        [--poke-style STYLE] [--known-mass REL] [--touch-alone] [--cache DIR] [--timeout 1800]
        [--json OUT.json] [--quiet]

For every effect (default: ``none`` and every SPEC effect) and
seeds FIRST..FIRST+N-1 it records a box in the MuJoCo world (one force-sensing finger,
the effect at the strength its seed draws, docs/effects.md; the pose observed at 0.5 mm
as by motion capture) and diagnoses the runs without the truth: the first half trains,
the second is held out.

Designs:

``--design toss`` (default; the 3-D counterpart of benchmarks/bench_diagnose.py's toss
    design): ``--runs`` runs of one object, each a toss (``tacest record --dim 3 --toss``:
    released in the air at a random orientation, height, speed and spin over the
    origin, seen flying, landing and coming to rest) followed by one poke of
    ``--poke-style`` (default ``high``: a push high on the object, which tips it)
    where it came to rest.  Flight shows drag, spin damping and a clock error; landings
    show restitution and a soft ground; the pokes show the sensor effects, com_offset and
    face friction.  ``--known-mass`` (default 0.02): the object was weighed (the
    truth's mass times exp(REL N(0, 1)), seeded per recording, as the mass prior of log
    sigma REL; 0: not weighed).
``--design pokes``: one run of ``--pokes`` pokes of ``--poke-style`` (default
    ``dynamic``), cut at its pokes into sub-runs (tacest.io.slicing.split_at_actions).
    With ``--touch-alone`` the pose is not observed (a tactile-exploration user's data;
    the 3-D diagnosis from touch alone, docs/estimation3d.md).  Each diagnosis runs in its own subprocess
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
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: m, sigma of the observed positions (motion capture); angles 0.5 mm / 5 cm
OBSERVE_POSE = 0.0005


#: random streams of the toss design: the releases, the weighing error
TOSS_STREAM, WEIGHING_STREAM = 7074, 7075


def toss_design(opts, n_runs: int, seed: int) -> list:
    """``n_runs`` runs of one object (``opts``): each a toss over the origin, then one
    random poke of ``opts.poke_style`` where it came to rest."""
    from tacest.sim3d.record import initial_state, simulate_pokes, state_from_run, toss_state

    rng_toss = np.random.default_rng([seed, TOSS_STREAM])
    state = initial_state(opts)
    runs = []
    for i in range(n_runs):
        run = simulate_pokes(toss_state(state, rng_toss, xy=(0.0, 0.0)), np.zeros((0, 8)), opts, noise_key=i + 1,
                             settle_first=True, random_pokes=1)
        state = state_from_run(run)
        runs.append(run)
    return runs


def worker(job: dict) -> dict:
    """Record and diagnose one recording (in this process); a JSON-able dict.  job: effect,
    seed, design, runs, pokes, style, known_mass."""
    from tacest.diagnosis.diagnose3d import diagnose_3d
    from tacest.io.slicing import split_at_actions
    from tacest.dims import record_sim
    from tacest.estimation.config import EstimatorConfig
    from tacest.sim.record import SimOptions

    effect, seed = job["effect"], job["seed"]
    opts = SimOptions(dim=3, seed=seed, pokes=job["pokes"], fingers=1, effects=[] if effect == "none" else [effect],
                      observe_pose=None if job.get("touch_alone") else OBSERVE_POSE, poke_style=job["style"]).validate()
    if job["design"] == "toss":
        runs = toss_design(opts, job["runs"], seed)
    else:
        runs = split_at_actions(record_sim(opts))
    truth = runs[0].truth.effects
    mass = float(runs[0].truth.mass)
    parts = [p.replace(filename=f"part{i}", truth=None) for i, p in enumerate(runs)]
    config = EstimatorConfig()
    if job["known_mass"] > 0:
        rng = np.random.default_rng([seed, sum(map(ord, effect)), WEIGHING_STREAM])
        config = config.updated({"prior": {"mass": mass * math.exp(job["known_mass"] * rng.normal()),
                                           "mass_log_sigma": job["known_mass"]}})
    t0 = time.perf_counter()
    d = diagnose_3d(parts, "box", config)
    wall = time.perf_counter() - t0
    right = next((e for e in d.effects if e["name"] == effect), None)
    return {"ok": True, "effect": effect, "seed": seed, "truth": truth, "verdict": d.verdict, "wall": wall,
            "right_reduction": None if right is None else right["reduction"],
            "effects": [{k: e[k] for k in ("name", "reduction", "gap_before", "gap_after", "params")}
                        for e in d.effects], "parts": len(parts), "reason": d.reason}


def run_job(job: dict, timeout) -> dict:
    effect, seed = job["effect"], job["seed"]
    cmd = [sys.executable, __file__, "--worker", json.dumps(job)]
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
    from tacest.sim.effects import EFFECT_NAMES
    from tacest.provenance import source_digest

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--effects", default=",".join(EFFECT_NAMES))
    ap.add_argument("--design", choices=("toss", "pokes"), default="toss")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--runs", type=int, default=4, help="toss design: runs (a toss and a poke each)")
    ap.add_argument("--pokes", type=int, default=6, help="pokes design: pokes of the one run")
    ap.add_argument("--poke-style", default=None, help="default: high (toss design), dynamic (pokes design)")
    ap.add_argument("--touch-alone", action="store_true", help="pokes design: no pose observations")
    ap.add_argument("--known-mass", type=float, default=None,
                    help="weighing error (log sigma) of the mass prior; 0: not weighed (default: 0.02 toss, 0 pokes)")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "tacest_bench_diagnose3d"))
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--json", default=None)
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    style = args.poke_style or ("high" if args.design == "toss" else "dynamic")
    known_mass = args.known_mass if args.known_mass is not None else (0.02 if args.design == "toss" else 0.0)
    if args.runs < 2 or args.pokes < 2 or known_mass < 0:
        ap.error("--runs and --pokes must be >= 2, --known-mass >= 0")
    if args.touch_alone and args.design == "toss":
        ap.error("--touch-alone is for the pokes design (a toss touches nothing)")
    effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    cache = Path(args.cache) / f"code_{source_digest(Path(__file__).resolve())}"
    cache.mkdir(parents=True, exist_ok=True)
    what = (f"toss design: {args.runs} runs of a toss and a {style} poke" if args.design == "toss"
            else f"{args.pokes} {style} pokes" + (", touch alone" if args.touch_alone else ", pose observed"))
    print(f"cache {cache}; {what}, mass weighed to {known_mass:g} (0: not), seeds {args.first_seed}.."
          f"{args.first_seed + args.seeds - 1}", flush=True)
    tag = ((f"toss{args.runs}" if args.design == "toss" else str(args.pokes)) + f"-{style}-km{known_mass:g}"
           + ("-touch" if args.touch_alone else ""))
    results = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for eff in effects:
            path = cache / f"{eff}-{seed}-{tag}.json"
            if path.is_file():
                r = json.loads(path.read_text())
            else:
                job = {"effect": eff, "seed": seed, "design": args.design, "runs": args.runs, "pokes": args.pokes,
                       "style": style, "known_mass": known_mass, "touch_alone": args.touch_alone}
                r = run_job(job, args.timeout)
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
        print(json.dumps(worker(json.loads(sys.argv[2]))))
    else:
        main()

"""Benchmark the 3-D estimator on the real tossed cube (ContactNets data).

    .venv/bin/python benchmarks/bench_cube.py [--train 0:30] [--heldout 100:150] [--shape box]
                                              [--restitution E ...] [--data DIR] [--json OUT.json] [--quiet]

1. ``tacest estimate toss_<train>.h5 ... --shape box -o EST.h5`` in a subprocess (the
   command a user runs): its wall time (Python start-up included) and the estimator's
   own ``wall_time`` attribute, per toss.
2. The estimate: box extents and their errors against the nominal edge 0.1048 m,
   ground friction, I/m (what pose-only data can tell about inertia), whether the mass
   is reported as not identifiable, and the solver status.  For reference, the edge
   implied by the observed resting height (2 x the median centre height over the last
   samples of the training tosses, where the cube lies on a face): what any rigid sharp
   box resting on the plane z = 0 must match.
3. Rollouts on held-out tosses with the project's own 3-D time-stepping model
   (tacest.estimation.rollout3d), from the first observed state (position and velocity
   by a parabola through the first 4 poses, rate from their quaternions), for the
   estimated model and for the nominal one (box 0.1048 m, mass 0.37 kg, inertia
   8.1e-4 kg·m² · 1, friction 0.15): position error as % of the cube's width (0.1048 m),
   averaged over samples then tosses (as ContactNets reports it), and the mean
   orientation error in degrees.  ``--restitution E ...`` adds the estimated model with
   the restitution law of coefficient E (tacest.model.effects_contact.Restitution; E = 0
   is its impact relief alone; the other parameters are the estimate's, made without it).

Targets (printed with PASS / FAIL): edge within 2 % of 0.1048 m; friction in 0.1-0.4;
estimated rollout error below the nominal's; wall time <= 2 s per training toss.
The exit status is 0 whether or not the targets are met (1 for bad arguments).
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

DATA = Path("/work/shared/datasets/contactnets-cube")
NOMINAL = {"edge": 0.1048, "mass": 0.37, "inertia": 8.1e-4, "friction": 0.15}
TARGET_EDGE_REL = 0.02
TARGET_FRICTION = (0.1, 0.4)
TARGET_SECONDS_PER_TOSS = 2.0
#: samples at the end of a toss taken as resting (the tosses end at rest on a face)
REST_SAMPLES = 10


def _range(text):
    a, b = (int(x) for x in text.split(":"))
    if not 0 <= a < b:
        raise argparse.ArgumentTypeError(f"bad range {text!r}: use START:STOP")
    return range(a, b)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", type=_range, default=_range("0:30"), help="toss indices to estimate from (START:STOP)")
    ap.add_argument("--heldout", type=_range, default=_range("100:150"), help="toss indices to roll out (START:STOP)")
    ap.add_argument("--shape", default="box")
    ap.add_argument("--config", type=Path, default=None, help="estimator config (TOML) passed to tacest estimate")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures as JSON")
    ap.add_argument("--restitution", type=float, nargs="*", default=[],
                    help="also roll out the estimated model with restitution of these coefficients")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))

    from tacest.estimation.rollout3d import TimeStepper3D, initial_state, shape_parameters
    from tacest.geometry.shapes3d import make_shape_3d
    from tacest.geometry.transforms import quat_angle
    from tacest.io.estimate import read_estimate
    from tacest.io.run import read_run

    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f} "
          f"on {os.cpu_count()} cores")
    train = [args.data / f"toss_{i:03d}.h5" for i in args.train]
    held = [args.data / f"toss_{i:03d}.h5" for i in args.heldout]
    missing = [str(p) for p in train + held if not p.is_file()]
    if missing:
        print(f"missing data files: {missing[:3]} ...", file=sys.stderr)
        return 1
    tacest = str(Path(sys.executable).parent / "tacest")
    out = {}
    with tempfile.TemporaryDirectory(prefix="bench_cube_") as tmp:
        est_path = Path(tmp) / "est.h5"
        cmd = [tacest, "estimate", *map(str, train), "--shape", args.shape, "-o", str(est_path)]
        if args.config is not None:
            cmd += ["--config", str(args.config)]
        log(f"$ tacest estimate toss_{args.train.start:03d}.h5 ... toss_{args.train.stop - 1:03d}.h5 "
            f"--shape {args.shape} -o EST.h5")
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        cli_wall = time.perf_counter() - t0
        log(proc.stderr.strip())
        if proc.returncode != 0:
            print(f"tacest estimate failed (exit {proc.returncode}): {proc.stderr.strip().splitlines()[-1:]}")
            return 0
        est = read_estimate(est_path)
    n = len(train)
    shape = make_shape_3d(est.shape)
    sp = shape_parameters(shape, est.vertices) if shape.name == "box" else None
    extents = np.ptp(est.vertices, axis=0)
    edge = float(np.mean(extents))
    rest = [read_run(p).pose_obs[-REST_SAMPLES:, 2] for p in train]
    rest_edge = 2.0 * float(np.median(np.concatenate(rest)))
    I = np.asarray(est.params["inertia"], float)
    mass = float(est.params["mass"])
    mu = float(est.params["friction_ground"])
    # augmentations (docs/estimation3d.md): rounded edges, ground offset (0 when not estimated)
    edge_radius = float(est.params.get("edge_radius", 0.0))
    ground_offset = float(est.params.get("ground_offset", 0.0))
    out["estimate"] = {
        "tosses": n, "solver_status": est.solver_status, "iterations": est.iterations,
        "cli_wall_time_s": cli_wall, "estimator_wall_time_s": est.wall_time,
        "seconds_per_toss": cli_wall / n, "extents_m": extents.tolist(), "edge_m": edge,
        "edge_rel_error": (edge - NOMINAL["edge"]) / NOMINAL["edge"],
        "extents_rel_error": ((extents - NOMINAL["edge"]) / NOMINAL["edge"]).tolist(),
        "rest_height_edge_m": rest_edge, "friction_ground": mu, "model": list(est.model),
        "edge_radius_m": edge_radius, "ground_offset_m": ground_offset,
        "inertia_over_mass_eig_m2": np.linalg.eigvalsh(I / mass).tolist(),
        "nominal_inertia_over_mass_m2": NOMINAL["inertia"] / NOMINAL["mass"],
        "mass_kg": mass, "mass_identifiable": bool(est.identifiable.get("mass", True)),
        "std": {k: v for k, v in est.std.items() if np.isfinite(v)},
    }
    e = out["estimate"]
    print(f"\nestimate from {n} tosses: {est.solver_status}, {est.iterations} iterations, "
          f"tacest estimate {cli_wall:.1f} s wall ({cli_wall / n:.2f} s per toss; estimator {est.wall_time:.1f} s)")
    print(f"  box extents {np.round(extents * 1000, 2)} mm, mean {edge * 1000:.2f} mm: "
          f"{100 * e['edge_rel_error']:+.2f} % vs nominal {NOMINAL['edge'] * 1000:.1f} mm "
          f"(per axis {np.round(100 * np.array(e['extents_rel_error']), 2)} %)")
    print(f"  augmentations {list(est.model)}: edge radius {edge_radius * 1000:.2f} mm, "
          f"ground offset {ground_offset * 1000:.2f} mm")
    print(f"  edge implied by the resting height above z = 0: {rest_edge * 1000:.2f} mm "
          f"({100 * (rest_edge - NOMINAL['edge']) / NOMINAL['edge']:+.2f} %)")
    print(f"  friction (ground) {mu:.3f};  I/m eigenvalues {np.round(np.linalg.eigvalsh(I / mass) * 1e3, 3)} e-3 m² "
          f"(nominal {NOMINAL['inertia'] / NOMINAL['mass'] * 1e3:.3f} e-3, uniform cube {edge ** 2 / 6 * 1e3:.3f} e-3)")
    print(f"  mass {mass:.3g} kg: " + ("estimated" if e["mass_identifiable"] else
                                     "NOT identifiable from pose-only data (the prior's value, information 0)"))

    # rollouts
    models = {
        "estimated": TimeStepper3D(shape, sp if sp is not None else np.linalg.norm(est.vertices, axis=1), mass, I, mu,
                                   dt=read_run(held[0]).dt, edge_radius=edge_radius, ground_height=ground_offset),
        "nominal": TimeStepper3D("box", [NOMINAL["edge"]] * 3, NOMINAL["mass"], NOMINAL["inertia"] * np.eye(3),
                                 NOMINAL["friction"], dt=read_run(held[0]).dt),
    }
    for e_r in args.restitution:
        models[f"est+e={e_r:g}"] = TimeStepper3D(
            shape, sp if sp is not None else np.linalg.norm(est.vertices, axis=1), mass, I, mu,
            dt=read_run(held[0]).dt, edge_radius=edge_radius, ground_height=ground_offset,
            effect_params={"restitution.e": e_r})
    width = NOMINAL["edge"]
    errs = {k: [] for k in models}
    t0 = time.perf_counter()
    for j, path in enumerate(held):
        run = read_run(path)
        P = run.pose_obs
        pose0, vel0 = initial_state(P, run.dt)
        for name, sim in models.items():
            S = sim.rollout(pose0, vel0, P.shape[0])
            pos = np.linalg.norm(S[:, :3] - P[:, :3], axis=1) / width * 100
            ang = np.degrees(quat_angle(S[:, 3:], P[:, 3:]))
            errs[name].append((float(pos.mean()), float(pos[-1]), float(ang.mean())))
        log(f"  rollout {j + 1}/{len(held)} {path.name}: " + ", ".join(
            f"{k} {errs[k][-1][0]:.1f} %" for k in models))
    roll_time = time.perf_counter() - t0
    steps = sum(read_run(p).n_samples - 1 for p in held)
    out["rollout"] = {"tosses": len(held), "wall_time_s": roll_time,
                      "unconverged_steps": {k: int(m.unconverged) for k, m in models.items()}, "steps": steps}
    print(f"\nrollouts on {len(held)} held-out tosses (toss_{args.heldout.start:03d}..{args.heldout.stop - 1:03d}), "
          f"{roll_time:.0f} s:")
    print(f"  {'model':<12} {'pos err mean':>13} {'median':>8} {'final':>8} {'angle err':>10}   (% of width, deg)")
    for name in models:
        a = np.array(errs[name])
        out["rollout"][name] = {"position_error_pct_mean": float(a[:, 0].mean()),
                                "position_error_pct_median": float(np.median(a[:, 0])),
                                "final_position_error_pct_mean": float(a[:, 1].mean()),
                                "angle_error_deg_mean": float(a[:, 2].mean()),
                                "per_toss_position_error_pct": a[:, 0].tolist()}
        r = out["rollout"][name]
        print(f"  {name:<12} {r['position_error_pct_mean']:12.1f} % {r['position_error_pct_median']:7.1f} % "
              f"{r['final_position_error_pct_mean']:7.1f} % {r['angle_error_deg_mean']:9.1f}°")
    better = np.mean(np.array(errs["estimated"])[:, 0] < np.array(errs["nominal"])[:, 0])
    out["rollout"]["fraction_estimated_better"] = float(better)
    print(f"  the estimated model tracks better on {100 * better:.0f} % of the held-out tosses")
    print("  simulation steps that did not converge (kept their last iterate): "
          + ", ".join(f"{k} {m.unconverged} of {steps}" for k, m in models.items()))

    targets = [
        ("edge within 2 % of 0.1048 m", abs(e["edge_rel_error"]) <= TARGET_EDGE_REL),
        ("friction in 0.1-0.4", TARGET_FRICTION[0] <= mu <= TARGET_FRICTION[1]),
        ("rollout error below nominal",
         out["rollout"]["estimated"]["position_error_pct_mean"] < out["rollout"]["nominal"]["position_error_pct_mean"]),
        ("<= 2 s per toss (tacest estimate wall time)", cli_wall / n <= TARGET_SECONDS_PER_TOSS),
        ("mass reported not identifiable", not e["mass_identifiable"]),
    ]
    print("\ntargets:")
    for name, ok in targets:
        print(f"  {'PASS' if ok else 'FAIL'}  {name}")
    out["targets"] = {name: bool(ok) for name, ok in targets}
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

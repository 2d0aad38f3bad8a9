"""Benchmark of the tactile video pipeline on synthetic 640x480 sequences with noise.

Prints, per seed and overall:
- contact-flag F1 (target >= 0.95) and the median / 90th percentile angle between the
  recovered and the true contact normal on frames where both say contact (target median
  <= 5 deg);
- throughput of the per-frame analysis (flow + HHD + contact) on in-memory 640x480 frames:
  wall-clock frames per second (target >= 60 on this 2-core machine) and CPU ms per frame;
- with --png: the end-to-end recorder (``record_video``) on a PNG folder, decoding
  included.
With --compare, the same for other flow settings (why the default is what it is).

    .venv/bin/python benchmarks/bench_video.py [--seeds 0 1 2] [--frames 300] [--dim 3]
                                               [--scene wander|box-press] [--png] [--compare]

Sequences: tacest.sensors.synth_tactile defaults (pixel noise sigma 3 grey levels, gain
drift 6 %, offset drift 6 levels, moving illumination gradient, contact shading 8 %,
shear 20 % of the indentation, 2-frame depth ramps at each contact's start and end,
contacts up to 60 deg from the apex).  ``--scene box-press``: the 2-D poking scene
(every contact at the dome's apex, a finger log consistent with a pressed box; with
``--png`` its runs are 2-D, the kind ``tacest estimate`` takes).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np

from tacest.sensors.synth_tactile import SynthConfig, generate, write_sequence
from tacest.sensors.tactile_flow import DetectSettings, FlowSettings, TactileFlow, decide_contacts

TARGET_F1 = 0.95
TARGET_MEDIAN_DEG = 5.0
TARGET_FPS = 60.0


def evaluate(seq, flow: FlowSettings, detect: DetectSettings | None = None) -> dict:
    """Analyse a sequence in memory; returns F1, angle errors and timing."""
    tf = TactileFlow(seq.calib, flow)
    tf.set_reference(seq.frames[0])
    tf.analyse(seq.frames[1])  # warm-up (allocations, DIS buffers)
    w0, c0 = time.perf_counter(), time.process_time()
    res = [tf.analyse(f) for f in seq.frames]
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    strength = np.array([r.strength for r in res])
    uv = np.array([r.uv for r in res])
    dec = decide_contacts(strength, detect)
    c, truth = dec.contact, seq.contact.astype(bool)
    tp = int(np.sum(c & truth))
    f1 = 2 * tp / max(int(c.sum() + truth.sum()), 1)
    both = c & truth
    n = seq.calib.object_normal(uv[both], dim=seq.dim)[0]
    ang = np.degrees(np.arccos(np.clip(np.sum(n * seq.normal[both], axis=1), -1, 1)))
    return {"f1": f1, "tp": tp, "fp": int(np.sum(c & ~truth)), "fn": int(np.sum(~c & truth)),
            "angles": ang, "fps": len(res) / wall, "cpu_ms": 1e3 * cpu / len(res), "noise": dec.noise}


def end_to_end_png(seq) -> dict:
    """record_video on a PNG folder: decoding, analysis, resampling, writing."""
    from tacest.sensors.video import VideoOptions, record_video

    with tempfile.TemporaryDirectory() as d:
        paths = write_sequence(seq, d)
        out = os.path.join(d, "run.h5")
        w0, c0 = time.perf_counter(), time.process_time()
        run, _ = record_video(paths["frames"], paths["calib"], paths["finger_log"], output=out,
                              options=VideoOptions())
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    return {"fps": len(seq.frames) / wall, "cpu_ms": 1e3 * cpu / len(seq.frames), "samples": run.n_samples,
            "dim": run.dim}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--dim", type=int, choices=(2, 3), default=None, help="default 3 (2 with --scene box-press)")
    p.add_argument("--scene", choices=("wander", "box-press"), default="wander")
    p.add_argument("--noise", type=float, default=3.0, help="pixel noise sigma, grey levels (default 3)")
    p.add_argument("--amplitude", type=float, default=1.0,
                   help="indentation amplitude relative to the generator's default (default 1)")
    p.add_argument("--max-polar", type=float, default=60.0, help="largest contact polar angle, deg (default 60)")
    p.add_argument("--png", action="store_true", help="also time the end-to-end recorder on a PNG folder")
    p.add_argument("--compare", action="store_true", help="also run other flow settings")
    a = p.parse_args(argv)
    if a.dim is None:
        a.dim = 2 if a.scene == "box-press" else 3
    if a.scene == "box-press" and a.dim != 2:
        p.error("--scene box-press is 2-D")

    configs = {"default (DIS tactile, scale 0.5, grid 8 px)": FlowSettings()}
    if a.compare:
        configs.update({
            "DIS medium, scale 0.5": FlowSettings(dis_preset="medium"),
            "DIS fast, scale 0.5": FlowSettings(dis_preset="fast"),
            "DIS ultrafast, scale 0.5": FlowSettings(dis_preset="ultrafast"),
            "DIS tactile, scale 1.0": FlowSettings(work_scale=1.0),
            "DIS tactile, scale 0.5, grid 16 px": FlowSettings(grid_px=16),
            "Farneback, scale 0.5": FlowSettings(method="farneback"),
        })
    print(f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} (other work slows the wall clock)")
    print(f"sequences: noise sigma {a.noise} grey levels, amplitude x{a.amplitude}, contacts up to {a.max_polar} deg, "
          f"dim {a.dim}, scene {a.scene}")
    seqs = []
    for seed in a.seeds:
        t0 = time.perf_counter()
        cfg = SynthConfig(n_frames=a.frames, seed=seed, dim=a.dim, noise_sigma=a.noise, max_polar_deg=a.max_polar,
                          scene=a.scene)
        cfg.indent_amplitude_px = a.amplitude * 0.02 * 0.46 * min(cfg.width, cfg.height)
        seqs.append(generate(cfg))
        print(f"seed {seed}: generated {a.frames} frames 640x480, {int(seqs[-1].contact.sum())} in contact "
              f"({time.perf_counter() - t0:.1f} s)")
    ok = True
    for name, flow in configs.items():
        print(f"\n== {name}")
        allang, tps, fps, fns, speeds, cpus = [], 0, 0, 0, [], []
        for seed, seq in zip(a.seeds, seqs):
            r = evaluate(seq, flow)
            allang.append(r["angles"])
            tps, fps, fns = tps + r["tp"], fps + r["fp"], fns + r["fn"]
            speeds.append(r["fps"])
            cpus.append(r["cpu_ms"])
            print(f"  seed {seed}: F1 {r['f1']:.3f} (fp {r['fp']}, fn {r['fn']}), normal error median "
                  f"{np.median(r['angles']):.2f} deg, p90 {np.percentile(r['angles'], 90):.2f} deg; "
                  f"{r['fps']:.0f} frames/s wall, {r['cpu_ms']:.1f} ms CPU/frame; noise level {r['noise']:.4f}")
        ang = np.concatenate(allang)
        f1 = 2 * tps / max(2 * tps + fps + fns, 1)
        med = float(np.median(ang))
        speed = float(np.median(speeds))
        print(f"  overall: F1 {f1:.3f}, normal error median {med:.2f} deg (p90 {np.percentile(ang, 90):.2f}), "
              f"{speed:.0f} frames/s (median over seeds), {np.median(cpus):.1f} ms CPU/frame")
        if flow == configs[next(iter(configs))]:
            verdict = [("F1", f1 >= TARGET_F1, f"{f1:.3f} >= {TARGET_F1}"),
                       ("median normal error", med <= TARGET_MEDIAN_DEG, f"{med:.2f} <= {TARGET_MEDIAN_DEG} deg"),
                       ("frames per second", speed >= TARGET_FPS, f"{speed:.0f} >= {TARGET_FPS:.0f}")]
            for what, good, detail in verdict:
                print(f"  target {what}: {'PASS' if good else 'FAIL'} ({detail})")
                ok &= good
    if a.png:
        print("\n== end to end: record_video on a PNG folder (decoding in a second thread)")
        for seed, seq in zip(a.seeds, seqs):
            r = end_to_end_png(seq)
            print(f"  seed {seed}: {r['fps']:.0f} frames/s wall, {r['cpu_ms']:.1f} ms CPU/frame, {r['samples']} samples, "
                  f"run dim {r['dim']}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark the serial recorder (tacest.sensors.serial_rig); prints its figures.

    .venv/bin/python benchmarks/bench_serial.py [--seconds 20] [--rate 1000] [--corrupt 0.01] [--fingers 1,3]

1. parse throughput: lines/s the Assembler takes from memory (1 % corrupted lines);
2. real time: the emulator (a separate process) plays at RATE samples/s with CORRUPT
   of its lines corrupted into a pseudo-terminal, the recorder reads it through
   pyserial until the emulator hangs up.  Target (issue "Real sensor inputs"): keep
   >= 99.9 % of the valid lines and lose none that were valid, i.e. every line the
   emulator sent intact is in the run file with its values (position, contact, force,
   normal) and not marked unknown in /quality/missing_finger.  Measured for each finger
   count of ``--fingers``: with F > 1 a corrupted line leaves only its own (sample,
   finger) unknown, its sibling lines are kept;
3. snapshot cost: time to write the whole run atomically for growing runs, and the
   interval the recorder then uses (SNAPSHOT_DUTY);
4. the alternative, HDF5 SWMR appends: cost per append, and whether a plain reader
   (tacest.io.run.read_run) can open the file while it is being written.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tacest.sensors.emulator import FaultLog, Faults, builtin_run, emulate_bytes, iter_chunks
from tacest.sensors.serial_rig import SNAPSHOT_DUTY, Assembler, record_serial, write_snapshot


def bench_parse(n=60000, corrupt=0.01):
    data, log = emulate_bytes(builtin_run(2, 1, n, 0.001), Faults(corrupt=corrupt, seed=1))
    a = Assembler()
    t0 = time.perf_counter()
    for i in range(0, len(data), 4096):
        a.feed(data[i:i + 4096])
    a.finish()
    dt = time.perf_counter() - t0
    s = a.summary()
    print(f"[parse]     {n} lines ({log.corrupted} corrupted) in {dt:.3f} s: {n / dt:,.0f} lines/s "
          f"({dt / n * 1e6:.1f} us/line); kept {s.kept_lines}, dropped {s.dropped_lines}")


#: values come back to half a unit in the printed decimals (emulator Precision():
#: position 6, force 4, normal 5 decimals; normals renormalised, so 2e-5)
TOL = {"position": 0.5e-6, "force": 0.5e-4, "normal": 2e-5}


def bench_realtime(seconds, rate, corrupt, fingers=1, seed=7):
    n = int(seconds * rate)
    faults = Faults(corrupt=corrupt, seed=seed)
    emu = subprocess.Popen([sys.executable, "-m", "tacest.sensors.emulator", "--samples", str(n), "--dt",
                            str(1.0 / rate), "--fingers", str(fingers), "--rate", str(rate), "--corrupt",
                            str(corrupt), "--seed", str(seed), "--pty"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    port = emu.stdout.readline().strip()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rec.h5"
        t0 = time.perf_counter()
        s = record_serial(port, baud=921600, output=out)
        wall = time.perf_counter() - t0
        _, emu_err = emu.communicate(timeout=30)
        from tacest.io.run import read_run

        run = read_run(out)
    # the same stream, regenerated (the emulator is deterministic for a seed): which
    # lines went out intact
    src = builtin_run(2, fingers, n, 1.0 / rate)
    log = FaultLog()
    for _ in iter_chunks(src, faults, log=log):
        pass
    # the run starts at the first sample of which a line was kept
    first = min(seq for seq, _ in log.intact)
    lost = 0
    for seq, f in log.intact:
        k = seq - first
        if k >= run.n_samples or run.missing_finger[k, f] or run.contact[k, f] != src.contact[seq, f] \
                or np.max(np.abs(run.finger_position[k, f] - src.finger_position[seq, f])) > TOL["position"] \
                or np.max(np.abs(run.force[k, f] - src.force[seq, f])) > TOL["force"] \
                or (src.contact[seq, f] and np.max(np.abs(run.normal[k, f] - src.normal[seq, f])) > TOL["normal"]):
            lost += 1
    kept_pct = 100.0 * (log.intact_lines - lost) / log.intact_lines
    print(f"[realtime]  {rate:g} samples/s x {fingers} finger(s) for {n / rate:g} s through {port}, "
          f"{100 * corrupt:g} % corrupted lines: valid lines sent {log.intact_lines}, in the run with their "
          f"values {log.intact_lines - lost} ({kept_pct:.3f} %), valid lines lost {lost}; recorder kept "
          f"{s.kept_lines} lines, dropped {s.dropped_lines} (sent corrupted {log.corrupted}); missing "
          f"{s.missing_samples} samples in {s.gaps} gaps ({s.partial_samples} partial); "
          f"wall {wall:.1f} s; {s.snapshots} snapshots, slowest {1e3 * s.snapshot_time_max:.1f} ms")
    ok = kept_pct >= 99.9 and lost == 0 and s.kept_lines == log.intact_lines
    print(f"[realtime]  target >= 99.9 % kept and 0 valid lost: {'MET' if ok else 'NOT MET'}")
    return ok


def bench_snapshot(lengths=(10_000, 100_000, 1_000_000), dim=3, fingers=1):
    with tempfile.TemporaryDirectory() as tmp:
        for T in lengths:
            src = builtin_run(dim, fingers, T, 0.001)
            run = src.replace(missing=np.zeros(T, np.uint8), source="serial")
            clock = src.time.copy()
            out = Path(tmp) / "snap.h5"
            costs = []
            for _ in range(3):
                t0 = time.perf_counter()
                write_snapshot(run, clock, out)
                costs.append(time.perf_counter() - t0)
            c = min(costs)
            mb = out.stat().st_size / 1e6
            interval = max(0.25, SNAPSHOT_DUTY * c)
            print(f"[snapshot]  T = {T:>9,} samples ({T / 1000:g} s at 1 kHz, {fingers} finger, {dim}-D): "
                  f"{mb:6.1f} MB written in {1e3 * c:7.1f} ms -> snapshot every {interval:.2f} s")


_SWMR_READER = """
import sys
from tacest.io.run import read_run
try:
    read_run(sys.argv[1]); print("ok")
except Exception as e:
    print(type(e).__name__ + ": " + str(e).splitlines()[0])
"""


def bench_swmr(T=100_000, chunk=250):
    import h5py

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "swmr.h5"
        f = h5py.File(path, "w", libver="latest")
        f.attrs.update(format="tacest.run", version=1, dim=3, dt=0.001, gravity=[0, 0, -9.81], source="serial")
        dsets = {"time": f.create_dataset("time", (0,), dtype="f8", maxshape=(None,), chunks=(4096,)),
                 "pos": f.create_dataset("robot/finger_position", (0, 1, 3), dtype="f8", maxshape=(None, 1, 3),
                                         chunks=(4096, 1, 3))}
        f.create_dataset("robot/finger_radius", data=[0.01])
        f.swmr_mode = True
        costs = []
        n = 0
        while n < T:
            t0 = time.perf_counter()
            for name, d in dsets.items():
                d.resize(n + chunk, axis=0)
                d[n:n + chunk] = np.arange(n, n + chunk).reshape((-1,) + (1,) * (d.ndim - 1)) * 1e-3
                d.flush()
            costs.append(time.perf_counter() - t0)
            n += chunk
        reader = subprocess.run([sys.executable, "-c", _SWMR_READER, str(path)], capture_output=True, text=True)
        f.close()
        print(f"[swmr]      append {chunk} samples: {1e3 * np.median(costs):.2f} ms median "
              f"(flat in T up to {T:,}); plain reader during the write: {reader.stdout.strip()[:160]}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--corrupt", type=float, default=0.01)
    ap.add_argument("--fingers", default="1,3", help="finger counts to measure, comma-separated")
    ap.add_argument("--skip-snapshot", action="store_true")
    a = ap.parse_args(argv)
    bench_parse(corrupt=a.corrupt)
    ok = True
    for fingers in (int(x) for x in a.fingers.split(",")):
        ok &= bench_realtime(a.seconds, a.rate, a.corrupt, fingers)
    if not a.skip_snapshot:
        bench_snapshot()
        bench_swmr()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

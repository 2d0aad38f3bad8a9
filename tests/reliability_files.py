"""Small valid files written by tacest's own writers, and the CLI as a user runs it, for
the reliability tests (outputs, interrupts, ties between files, exit statuses, fuzzing).

The estimate and plan files are stand-ins that need no solve: an estimate holds the
simulated run's truth (shape, poses, parameters) as if the estimator had found it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from tacest.estimation.floor import TERMS
from tacest.io.estimate import Estimate, RunEstimate, write_estimate
from tacest.io.h5util import sha256_file
from tacest.io.plan import POKE_NAMES, Plan, write_plan
from tacest.io.run import read_run, write_run
from tacest.sim.record import SimOptions, record_sim

TACEST = str(Path(sys.executable).parent / "tacest")


def tacest(*args, cwd=None, env=None, timeout=300):
    """Run the installed ``tacest`` with ``args``; returns the CompletedProcess."""
    return subprocess.run([TACEST, *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          env=None if env is None else {**os.environ, **env})


def one_error_line(res, prefix="tacest: error:"):
    """The single stderr line of a failed command (asserts there is exactly one, no traceback)."""
    assert "Traceback" not in res.stderr, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(prefix), lines[0]
    return lines[0]


def make_run(path, seed=1, pokes=2, **options) -> Path:
    """A simulated 2-D run file (with truth) from tacest.sim.record."""
    write_run(record_sim(SimOptions(seed=seed, pokes=pokes, **options)), path)
    return Path(path)


def truth_estimate(run_paths, path) -> Path:
    """An estimate file of ``run_paths`` holding their truth, with the source SHA-256 the
    estimator records (the poses of each run; shape and parameters of the first)."""
    runs = [read_run(p) for p in run_paths]
    tr = runs[0].truth
    est = Estimate(
        dim=2, shape="box", vertices=tr.vertices,
        params={"mass": tr.mass, "inertia": tr.inertia, "friction_ground": tr.friction_ground,
                "friction_finger": tr.friction_finger},
        runs=[RunEstimate(pose=r.truth.pose, velocity=np.zeros_like(r.truth.pose),
                          impulses={"finger_0": np.zeros((r.n_samples, 2))},
                          residuals={t: np.zeros(r.n_samples) for t in TERMS},
                          source_file=str(p), source_sha256=sha256_file(p)) for r, p in zip(runs, run_paths)],
        solver_status="Solve_Succeeded", success=True, iterations=1, objective=1.0)
    write_estimate(est, path)
    return Path(path)


def poke_plan(path, run_paths=(), estimate_path=None) -> Path:
    """A plan file of one poke toward the origin, tied to ``run_paths`` (attrs
    ``runs_sha256``) and ``estimate_path`` when given."""
    import json

    chosen = np.array([0.0, 0.5, 0.0, 0.02, 0.02, 0.04])
    extra = {"runs_sha256": json.dumps([sha256_file(p) for p in run_paths])} if run_paths else {}
    write_plan(Plan(chosen=chosen, candidates=chosen[None], scores=np.array([1.0]), method="eig", score="logdet",
                    estimate_sha256=sha256_file(estimate_path) if estimate_path else "", names=list(POKE_NAMES),
                    extra_attrs=extra), path)
    return Path(path)


def interrupt_when(args, marker=None, cwd=None, delay=0.3, timeout=300, group=False):
    """Start ``tacest args``, send SIGINT ``delay`` s after a stderr line contains
    ``marker`` (or after ``delay`` s when ``marker`` is None), and return (exit status,
    the non-empty stderr lines from then on).  ``group``: to its whole process group, as
    Ctrl-C in a terminal does (its forked workers get it too)."""
    p = subprocess.Popen([TACEST, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         cwd=cwd, start_new_session=group)
    if marker is not None:
        t0 = time.monotonic()
        seen = []
        for line in p.stderr:
            seen.append(line.rstrip("\n"))
            if marker in line:
                break
            if time.monotonic() - t0 > timeout:
                p.kill()
                raise AssertionError(f"no {marker!r} within {timeout} s: {seen[-5:]}")
        else:
            p.wait()
            raise AssertionError(f"the command ended (status {p.returncode}) before {marker!r}: {seen[-5:]}")
    time.sleep(delay)
    assert p.poll() is None, f"the command ended (status {p.returncode}) before the interrupt"
    if group:
        os.killpg(p.pid, signal.SIGINT)
    else:
        p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=timeout)
    return p.returncode, [ln for ln in err.splitlines() if ln.strip()]

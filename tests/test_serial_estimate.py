"""Serial to estimate: the emulator plays a recorded 2-D simulated run (two fingers, some
lines corrupted) into a pseudo-terminal, ``tacest record --source serial`` records it,
and ``tacest estimate`` accepts the result."""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tacest.estimation.data import touching
from tacest.estimation.estimator import ImplicitEstimator
from tacest.io.run import read_run, write_run
from tacest.sim.record import SimOptions, record_sim

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals")

TACEST = Path(sys.executable).with_name("tacest")
CLI = [str(TACEST)] if TACEST.exists() else [sys.executable, "-m", "tacest"]
EMULATOR = [sys.executable, "-m", "tacest.sensors.emulator"]
TOL_POS = 0.5e-6  # m: positions are printed with 6 decimals (half a unit in the last place)
TOL_FORCE = 0.5e-4  # N: forces with 4 decimals
#: IPOPT capped at a few iterations: the test is that the recorded run is accepted and its
#: problem built and solved, not how far a solve gets
TINY_SOLVER = "[solver]\nmax_iter = 3\nstage_max_iter = 3\n"


def test_emulated_sim_run_recorded_over_serial_is_accepted_by_estimate(tmp_path):
    sim_path = tmp_path / "sim.h5"
    src = record_sim(SimOptions(dim=2, object_spec="box", seed=3, pokes=2, fingers=2))
    write_run(src, sim_path)
    emu = subprocess.Popen(EMULATOR + [str(sim_path), "--rate", "0", "--corrupt", "0.02", "--seed", "1",
                                       "--pty", "--wait", "30"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True)
    try:
        port = emu.stdout.readline().strip()
        assert port.startswith("/dev/"), emu.stderr.read() if emu.poll() is not None else port
        out = tmp_path / "serial.h5"
        rec = subprocess.run(CLI + ["record", "--source", "serial", "--port", port, "--duration", "60", "-o", str(out)],
                             capture_output=True, text=True, timeout=120)
    finally:
        if emu.poll() is None:
            emu.terminate()
        _, emu_err = emu.communicate(timeout=30)
    assert rec.returncode == 0, rec.stderr
    n_corrupted = int(re.search(r"(\d+) corrupted", emu_err).group(1))
    assert n_corrupted > 0

    run = read_run(out)
    assert (run.dim, run.n_fingers, run.source, run.n_samples) == (2, 2, "serial", src.n_samples)
    # each corrupted line leaves its own (sample, finger) unknown, nothing else
    assert int(run.missing_finger.sum()) == n_corrupted
    np.testing.assert_array_equal(run.missing, run.missing_finger.any(axis=1))
    ok = ~run.missing_finger.astype(bool)
    np.testing.assert_allclose(run.finger_position[ok], src.finger_position[ok], atol=TOL_POS, rtol=0)
    np.testing.assert_allclose(run.force[ok], src.force[ok], atol=TOL_FORCE, rtol=0)
    np.testing.assert_array_equal(run.contact[ok], src.contact[ok])
    partial = run.missing_finger.sum(axis=1) == 1
    assert partial.any() and f"({int(partial.sum())} partial" in rec.stderr

    est = ImplicitEstimator([run], "box")  # accepted: 2-D, two fingers, its problem built
    assert est.structures[0].F == 2
    np.testing.assert_array_equal(touching(run), run.contact.astype(bool) & ok)

    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY_SOLVER)
    est_path = tmp_path / "est.h5"
    e = subprocess.run(CLI + ["estimate", str(out), "--shape", "box", "--config", str(cfg), "--quiet",
                              "-o", str(est_path)], capture_output=True, text=True, timeout=300)
    if e.returncode == 0:
        assert est_path.exists()
    else:
        lines = e.stderr.strip().splitlines()
        assert e.returncode == 2 and len(lines) == 1, e.stderr
        assert lines[0].startswith("tacest: error: IPOPT failed"), lines[0]
        assert not est_path.exists()

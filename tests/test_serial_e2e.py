"""End to end: the emulator and ``tacest record --source serial`` through a real
pseudo-terminal (os.openpty) and through pyserial's ``loop://``."""

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from tacest.io.run import read_run
from tacest.sensors.emulator import Faults, builtin_run, iter_chunks, play
from tacest.sensors.serial_rig import Assembler, record_serial

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs pseudo-terminals")

TACEST = Path(sys.executable).with_name("tacest")
CLI = [str(TACEST)] if TACEST.exists() else [sys.executable, "-m", "tacest"]
EMULATOR = [sys.executable, "-m", "tacest.sensors.emulator"]
TOL_POS = 0.5e-6  # m: positions are printed with 6 decimals (half a unit in the last place)


def _start_emulator(*args):
    """Start the emulator on a new pty; return (process, slave path)."""
    proc = subprocess.Popen(EMULATOR + list(args) + ["--pty", "--wait", "30"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    path = proc.stdout.readline().strip()
    assert path.startswith("/dev/"), (path, proc.stderr.read() if proc.poll() is not None else "")
    return proc, path


def _stop(proc):
    if proc.poll() is None:
        proc.terminate()
    try:
        return proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()


def test_cli_records_from_a_pty_until_the_emulator_hangs_up(tmp_path):
    out = tmp_path / "rec.h5"
    emu, port = _start_emulator("--dim", "2", "--fingers", "2", "--samples", "3000", "--dt", "0.001",
                                "--rate", "2000", "--corrupt", "0.01", "--garbage", "0.005", "--drop", "0.003",
                                "--repeat-header-every", "500", "--disconnect-after", "4000", "--seed", "5")
    try:
        rec = subprocess.run(CLI + ["record", "--source", "serial", "--port", port, "--duration", "30",
                                    "-o", str(out)], capture_output=True, text=True, timeout=60)
    finally:
        _, emu_err = _stop(emu)
    assert rec.returncode == 0, rec.stderr
    assert "link closed" in rec.stderr and "then hung up" in emu_err
    summary = [ln for ln in rec.stderr.splitlines() if ln.startswith("kept ")]
    assert summary and "dropped" in summary[0] and "missing" in summary[0]
    run = read_run(out)
    assert run.source == "serial" and run.n_fingers == 2 and run.dt == 0.001
    # 4000 lines minus headers and garbage, two lines per sample, some samples lost
    assert 1800 <= run.n_samples <= 2000
    assert 0 < int(run.missing.sum()) < 150
    src = builtin_run(2, 2, 3000, 0.001)
    ok = run.missing == 0
    np.testing.assert_allclose(run.finger_position[ok], src.finger_position[:run.n_samples][ok],
                               atol=TOL_POS, rtol=0)


def test_ctrl_c_ends_the_cli_recording_with_a_valid_file(tmp_path):
    out = tmp_path / "rec.h5"
    emu, port = _start_emulator("--samples", "200000", "--dt", "0.001", "--rate", "1000")
    try:
        # SIGINT as at a terminal: a test run started in the background of a
        # non-interactive shell ignores SIGINT, its children inherit that, and Python then
        # installs no KeyboardInterrupt handler (the recorder never saw the Ctrl-C)
        rec = subprocess.Popen(CLI + ["record", "--source", "serial", "--port", port, "-o", str(out)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        # wait until the first snapshot is on disk, then a little more
        t_end = time.monotonic() + 30
        while not out.exists() and time.monotonic() < t_end:
            time.sleep(0.05)
        assert out.exists()
        read_run(out)  # valid while recording
        time.sleep(0.5)
        rec.send_signal(signal.SIGINT)
        # generous: the recorder ends at once, but on a loaded 2-core machine (other test
        # processes, the emulator) building and writing the final file took over 30 s
        _, err = rec.communicate(timeout=120)
    finally:
        _stop(emu)
    assert rec.returncode == 0, err
    assert "interrupted (Ctrl-C)" in err and "kept " in err
    run = read_run(out)
    assert run.n_samples > 300 and run.missing.sum() == 0


def test_cli_nothing_received_exits_2_with_one_line_and_no_file(tmp_path):
    out = tmp_path / "rec.h5"
    rec = subprocess.run(CLI + ["record", "--source", "serial", "--port", "loop://", "--duration", "0.3",
                                "--quiet", "-o", str(out)], capture_output=True, text=True, timeout=60)
    assert rec.returncode == 2
    lines = rec.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tacest: error: no run recorded from loop://")
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_cli_port_that_cannot_be_opened_exits_2(tmp_path):
    rec = subprocess.run(CLI + ["record", "--source", "serial", "--port", "/dev/nonexistent-tty",
                                "-o", str(tmp_path / "x.h5")], capture_output=True, text=True, timeout=60)
    assert rec.returncode == 2
    lines = rec.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot open serial port /dev/nonexistent-tty" in lines[0]


def test_loop_url_round_trip(tmp_path, caplog):
    """Emulator and recorder share one pyserial loop:// port (its queue holds 4 kB, so
    the emulator writes from a thread)."""
    out = tmp_path / "rec.h5"
    src = builtin_run(3, 1, 1500, dt=0.001)
    port = serial.serial_for_url("loop://", timeout=0.05)
    writer = threading.Thread(target=play, args=(iter_chunks(src, Faults(corrupt=0.01, seed=2)), port.write, 0.0),
                              daemon=True)
    writer.start()
    # ends on --duration: a loop never hangs up; 3 s is > 10x what 1500 lines need here
    with caplog.at_level(logging.INFO, logger="tacest"):
        s = record_serial(port, duration=3.0, output=out)
    writer.join(timeout=5)
    port.close()
    assert "duration" in s.stop_reason
    run = read_run(out)
    assert run.n_samples == s.kept_samples + s.missing_samples
    assert s.dropped["checksum"] + s.dropped["malformed"] == s.dropped_lines > 0
    ok = run.missing == 0
    np.testing.assert_allclose(run.finger_position[ok], src.finger_position[:run.n_samples][ok], atol=TOL_POS, rtol=0)


def test_emulator_writes_a_file_that_the_assembler_reads(tmp_path):
    dump = tmp_path / "stream.txt"
    r = subprocess.run(EMULATOR + ["--dim", "3", "--fingers", "2", "--samples", "100", "--out", str(dump)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    a = Assembler()
    a.feed(dump.read_bytes())
    a.finish()
    assert a.summary().kept_samples == 100 and a.header.dim == 3

"""Serial recorder (tacest.sensors.serial_rig) on in-memory byte streams: every link
fault of the issue, the always-valid output file, and the emulator round trip."""

import logging
import math
import time

import numpy as np
import pytest
import serial

from tacest.errors import TacestError
from tacest.io.run import read_run
from tacest.sensors.emulator import Faults, builtin_run, emulate_bytes, header_for_run, iter_chunks
from tacest.sensors.serial_protocol import Precision, format_header, format_sample, with_checksum
from tacest.sensors.serial_rig import Assembler, record_serial, record_stream

HDR = b"#TACEST,1,dim=2,fingers=1,radius=0.010,dt=0.01\n"
HDR2F = b"#TACEST,1,dim=2,fingers=2,radius=0.010;0.012,dt=0.01\n"
P = Precision()
# Round-trip tolerances: the protocol prints fixed decimals, so a value comes back to
# within half a unit in its last place (plus float64 rounding of the parse, < 1e-15).
TOL_POS = 0.5 * 10.0 ** -P.position   # m
TOL_FORCE = 0.5 * 10.0 ** -P.force    # N
TOL_TIME = 0.5 * 10.0 ** -P.t         # s
# normals: each component is rounded by <= 0.5e-5 and the vector renormalised; the
# renormalisation moves a component by at most | |n| - 1 | <= sqrt(3) * 0.5e-5, so
# 2e-5 covers both with margin.
TOL_NORMAL = 2e-5


def line(seq, t=None, finger=0, pos=(0.0, 0.05), contact=0, force=(0.0, 0.0), normal=None):
    """One valid S line (bytes with newline); t defaults to seq * 0.01 s."""
    t = seq * 0.01 if t is None else t
    return (format_sample(seq, t, finger, pos, contact, force, normal) + "\n").encode()


def stream(seqs, fingers=1):
    """Valid lines for the given seq values, x position = seq mm, contact on odd seq."""
    out = b""
    for s in seqs:
        for f in range(fingers):
            c = s % 2
            out += line(s, finger=f, pos=(s * 1e-3, 0.05 + f), contact=c, force=(0.1 * c, -0.2 * c),
                        normal=(0.0, 1.0) if c else None)
    return out


def assemble(data, chunk=None):
    a = Assembler()
    if chunk is None:
        a.feed(data)
    else:
        for i in range(0, len(data), chunk):
            a.feed(data[i:i + chunk])
    a.finish()
    return a


class FakeStream:
    """A serial-like stream: ``read`` hands out ``chunks`` one per call, then ends with
    EOF (b"") or raises ``end`` (SerialException: unplugged; KeyboardInterrupt: Ctrl-C).
    ``on_read(i)`` runs before each read (used to inspect the output file mid-run)."""

    def __init__(self, chunks, end=None, on_read=None):
        self.chunks = list(chunks)
        self.end = end
        self.on_read = on_read
        self.i = 0

    def read(self, n):
        if self.on_read:
            self.on_read(self.i)
        self.i += 1
        if self.chunks:
            return self.chunks.pop(0)
        if self.end is not None:
            raise self.end
        return b""


def quiet(*a, **k):
    pass


# ---------------------------------------------------------------------------------
# faults, one at a time


def test_clean_stream():
    a = assemble(HDR + stream(range(10)))
    s = a.summary()
    assert (s.kept_samples, s.kept_lines, s.dropped_lines, s.missing_samples, s.gaps) == (10, 10, 0, 0, 0)
    run, clock = a.to_run()
    run.validate()
    np.testing.assert_allclose(run.time, np.arange(10) * 0.01, atol=1e-15)
    np.testing.assert_allclose(clock, np.arange(10) * 0.01, atol=TOL_TIME)
    assert run.missing.sum() == 0


def test_bad_checksum_dropped_and_counted():
    bad = bytearray(line(3))
    bad[6] = ord("9") if bad[6] != ord("9") else ord("8")  # one digit of the clock changed
    a = assemble(HDR + stream(range(3)) + bytes(bad) + stream(range(4, 6)))
    s = a.summary()
    assert s.dropped["checksum"] == 1 and s.dropped_lines == 1
    assert s.kept_samples == 5 and s.missing_samples == 1 and s.gaps == 1


def test_truncated_line_dropped_and_glued_line_recovered():
    cut = line(3)[:17] + b"\n"                 # cut short, newline survived
    glued = line(5)[:20] + line(6)             # cut short, newline lost: glued onto seq 6
    a = assemble(HDR + stream(range(3)) + cut + line(4) + glued + stream(range(7, 9)))
    s = a.summary()
    # both truncated pieces are malformed; seq 6 is resynchronised from its own 'S,'
    assert s.dropped == {**s.dropped, "malformed": 2} and s.dropped_lines == 2
    assert s.kept_samples == 7  # 0, 1, 2, 4, 6, 7, 8
    run, _ = a.to_run()
    np.testing.assert_array_equal(run.missing, [0, 0, 0, 1, 0, 1, 0, 0, 0])


def test_garbage_bytes_including_non_utf8():
    junk = [b"\xff\xfe\x00\x81garbage\x9c\n", b"\x00\x00\x00\n", b"hello world\n", b"\r\n",  # blank: ignored
            b"#DEBUG boot ok\n", bytes(range(11, 256)) + b"\n"]
    data = HDR + stream(range(2)) + b"".join(junk) + stream(range(2, 4))
    s = assemble(data).summary()
    assert s.dropped["malformed"] == 5 and s.dropped_lines == 5
    assert s.kept_samples == 4 and s.missing_samples == 0


def test_garbage_glued_in_front_of_a_line_is_recovered():
    data = HDR + stream(range(2)) + b"\xff\xfeS,zz" + line(2) + stream(range(3, 4))
    s = assemble(data).summary()
    assert s.kept_samples == 4 and s.dropped == {**s.dropped, "malformed": 1}


def test_wrong_field_count_and_unparsable_number():
    few = (with_checksum("S,2,0.02,0,0.002,0.05,0,0,0,") + "\n").encode()       # 10 fields
    many = (with_checksum("S,3,0.03,0,0.003,0.05,0,0,0,,,,") + "\n").encode()   # 13 fields
    nan = (with_checksum("S,4,0.04,0,nope,0.05,0,0,0,,") + "\n").encode()
    data = HDR + stream(range(2)) + few + many + nan + stream(range(5, 7))
    s = assemble(data).summary()
    assert s.dropped["fields"] == 2 and s.dropped["number"] == 1 and s.dropped_lines == 3
    assert (s.kept_samples, s.missing_samples, s.gaps) == (4, 3, 1)


def test_contact_with_bad_normal_is_dropped():
    no_normal = (with_checksum("S,2,0.02,0,0.002,0.05,1,0.1,-0.2,,") + "\n").encode()
    long_normal = line(3, contact=1, normal=(0.0, 1.2))
    s = assemble(HDR + stream(range(2)) + no_normal + long_normal + stream(range(4, 5))).summary()
    assert s.dropped["normal"] == 2 and s.missing_samples == 2


def test_lines_before_first_header_dropped():
    a = assemble(stream(range(3)) + HDR + stream(range(3, 6)))
    s = a.summary()
    assert s.dropped["before_header"] == 3 and s.kept_samples == 3
    run, _ = a.to_run()
    assert run.n_samples == 3  # the run starts at the first kept seq (3): time 0


def test_repeated_identical_header_is_fine():
    # the same settings written differently (0.010 vs 0.01, extra key) count as identical
    again = b"#TACEST,1,dim=2,fingers=1,radius=0.01,dt=0.010,fw=1.2\n"
    a = assemble(HDR + stream(range(3)) + HDR + stream(range(3, 5)) + again + stream(range(5, 8)))
    s = a.summary()
    assert s.headers == 3 and s.kept_samples == 8 and s.dropped_lines == 0 and not a.stopped


def test_changed_header_mid_stream_stops_the_run():
    other = b"#TACEST,1,dim=2,fingers=1,radius=0.010,dt=0.005\n"
    a = assemble(HDR + stream(range(5)) + other + stream(range(100, 110)))
    assert a.stopped and "settings changed" in a.stop_reason and "dt=0.005" in a.stop_reason
    s = a.summary()
    assert s.kept_samples == 5
    run, _ = a.to_run()
    assert run.dt == 0.01 and run.n_samples == 5


def test_changed_header_before_any_sample_kept_replaces_it():
    other = b"#TACEST,1,dim=2,fingers=2,radius=0.010;0.012,dt=0.01\n"
    a = assemble(HDR + other + stream(range(4), fingers=2))
    assert not a.stopped and a.header.fingers == 2 and a.summary().kept_samples == 4


def test_bad_header_counted_then_good_one_used():
    a = assemble(b"#TACEST,7,dim=2\n" + stream(range(2)) + HDR + stream(range(2, 5)))
    s = a.summary()
    assert s.dropped["header"] == 1 and s.dropped["before_header"] == 2 and s.kept_samples == 3


def test_missing_seq_is_a_gap_with_placeholders():
    # seq 3, 4, 5 never sent; seq 2 is in contact (even seqs are not: see stream())
    a = assemble(HDR + stream([0, 1, 2, 6, 7]))
    s = a.summary()
    assert (s.kept_samples, s.missing_samples, s.gaps) == (5, 3, 1)
    assert "missing 3 samples in 1 gaps" in s.line()
    run, clock = a.to_run()
    run.validate()
    np.testing.assert_array_equal(run.missing, [0, 0, 0, 1, 1, 1, 0, 0])
    np.testing.assert_allclose(run.time, np.arange(8) * 0.01, atol=1e-15)  # uniform over seq
    # placeholders: position linearly interpolated (x = seq mm), contact 0, force 0, normal NaN
    np.testing.assert_allclose(run.finger_position[3:6, 0, 0], [3e-3, 4e-3, 5e-3], atol=TOL_POS)
    assert run.contact[3:6].sum() == 0 and np.all(run.force[3:6] == 0) and np.all(np.isnan(run.normal[3:6]))
    assert np.all(np.isnan(clock[3:6])) and np.all(np.isfinite(clock[[0, 1, 2, 6, 7]]))


def test_partial_sample_keeps_the_line_that_arrived_and_marks_only_the_missing_finger():
    data = HDR2F + stream(range(3), fingers=2)
    # finger 0 of seq 3 never arrives; finger 1 touches with a force and a normal
    data += line(3, finger=1, pos=(0.0031, 1.05), contact=1, force=(0.3, -0.1), normal=(0.6, 0.8))
    data += stream(range(4, 6), fingers=2)
    a = assemble(data)
    s = a.summary()
    assert (s.kept_samples, s.kept_lines, s.missing_samples, s.gaps) == (5, 11, 1, 1)
    assert (s.partial_samples, s.partial_lines, s.dropped_lines) == (1, 1, 0)
    assert s.line().endswith("missing 1 samples in 1 gaps (1 partial: their 1 line kept)")
    run, clock = a.to_run()
    run.validate()
    np.testing.assert_array_equal(run.missing, [0, 0, 0, 1, 0, 0])
    expect = np.zeros((6, 2), np.uint8)
    expect[3, 0] = 1
    np.testing.assert_array_equal(run.missing_finger, expect)
    # finger 1 keeps everything it sent
    np.testing.assert_allclose(run.finger_position[3, 1], [0.0031, 1.05], atol=TOL_POS)
    assert run.contact[3, 1] == 1
    np.testing.assert_allclose(run.force[3, 1], [0.3, -0.1], atol=TOL_FORCE)
    np.testing.assert_allclose(run.normal[3, 1], [0.6, 0.8], atol=TOL_NORMAL)
    # finger 0 holds placeholders: interpolated position, contact 0, force 0, normal NaN
    np.testing.assert_allclose(run.finger_position[3, 0], [0.003, 0.05], atol=TOL_POS)
    assert run.contact[3, 0] == 0 and np.all(run.force[3, 0] == 0) and np.all(np.isnan(run.normal[3, 0]))
    assert np.isfinite(clock[3])  # the line that arrived carried the rig clock


def test_duplicate_and_late_lines_are_order_drops():
    data = HDR + stream(range(4)) + line(3) + line(1) + stream(range(4, 6))
    s = assemble(data).summary()
    assert s.dropped["order"] == 2 and s.kept_samples == 6


def test_seq_wraps_around_uint16():
    seqs = list(range(65533, 65536)) + list(range(0, 3))
    a = assemble(HDR + stream(seqs))
    s = a.summary()
    assert (s.kept_samples, s.missing_samples) == (6, 0) and not a.stopped
    # a wrap with a gap across it: 65535 -> 1 means seq 0 (unwrapped 65536) is missing
    a = assemble(HDR + stream([65534, 65535, 1, 2]))
    assert (a.summary().kept_samples, a.summary().missing_samples) == (4, 1)


def test_device_restart_stops_the_run():
    a = assemble(HDR + stream(range(100, 120)) + HDR + stream(range(0, 10)))
    assert a.stopped and "restarted" in a.stop_reason
    assert a.summary().kept_samples == 20


def test_huge_seq_jump_stops_the_run():
    a = Assembler(max_gap=1.0)  # 1 s = 100 samples at dt = 0.01
    a.feed(HDR + stream(range(5)) + stream([500]))
    assert a.stopped and "jumped" in a.stop_reason and a.summary().kept_samples == 5


def test_overlong_line_is_dropped_without_buffering():
    a = Assembler()
    a.feed(HDR + stream(range(2)))
    for _ in range(100):
        a.feed(b"x" * 1000)  # 100 kB without a newline
    assert len(a._buf) <= 1000
    a.feed(b"\n" + stream(range(2, 4)))
    a.finish()
    s = a.summary()
    assert s.dropped["malformed"] >= 1 and s.kept_samples == 4


def test_chunking_does_not_matter():
    data, _ = emulate_bytes(builtin_run(2, 2, 300), Faults(corrupt=0.05, truncate=0.02, garbage=0.02, drop=0.02,
                                                           drop_line=0.02, repeat_header_every=50, seed=4))
    whole = assemble(data)
    for chunk in (1, 7, 4096):
        part = assemble(data, chunk)
        assert part.summary().as_dict() == whole.summary().as_dict()
        r1, _ = whole.to_run()
        r2, _ = part.to_run()
        np.testing.assert_array_equal(r1.finger_position, r2.finger_position)


def test_emulator_fault_counts_match_recorder_counts():
    run = builtin_run(2, 1, 5000)
    faults = Faults(corrupt=0.01, truncate=0.005, garbage=0.005, drop=0.003, repeat_header_every=400, seed=11)
    data, log = emulate_bytes(run, faults)
    s = assemble(data).summary()
    assert log.corrupted > 20 and log.truncated > 10 and log.garbage > 10 and len(log.dropped_samples) > 5
    # every faulty line is dropped, every intact line is kept (one finger: line = sample)
    assert s.dropped_lines == log.corrupted + log.truncated + log.garbage
    assert s.kept_lines == log.intact_lines
    assert s.headers == log.headers
    lost = log.corrupted + log.truncated + len(log.dropped_samples)
    first, last = log.intact[0][0], log.intact[-1][0]
    assert s.missing_samples == (last - first + 1) - log.intact_lines
    assert s.missing_samples <= lost


# ---------------------------------------------------------------------------------
# round trip through the emulator


@pytest.mark.parametrize("dim,fingers,force", [(2, 1, True), (2, 3, True), (3, 2, True), (3, 1, False)])
def test_round_trip_equals_original_streams(tmp_path, dim, fingers, force):
    src = builtin_run(dim, fingers, 400, dt=0.002)
    src = src.replace(time=src.time + 3.0)  # the rig clock needs not start at 0
    if not force:
        src = src.replace(force=None)
    data, _ = emulate_bytes(src)
    out = tmp_path / "rec.h5"
    summary = record_stream(FakeStream([data[i:i + 999] for i in range(0, len(data), 999)]), out)
    assert summary.kept_samples == 400 and summary.dropped_lines == 0 and summary.stop_reason == "end of input"
    rec = read_run(out)
    assert (rec.dim, rec.n_fingers, rec.source) == (dim, fingers, "serial")
    assert rec.dt == pytest.approx(src.dt, rel=1e-12)  # dt is printed with 9 significant digits
    np.testing.assert_allclose(rec.time, src.time - src.time[0], atol=1e-12)  # k*dt vs accumulated sums
    np.testing.assert_allclose(rec.finger_radius, src.finger_radius, rtol=1e-6)  # 6 significant digits
    np.testing.assert_allclose(rec.gravity, src.gravity)
    np.testing.assert_allclose(rec.finger_position, src.finger_position, atol=TOL_POS, rtol=0)
    np.testing.assert_array_equal(rec.contact, src.contact)
    on = src.contact.astype(bool)
    np.testing.assert_allclose(rec.normal[on], src.normal[on], atol=TOL_NORMAL, rtol=0)
    assert np.all(np.isnan(rec.normal[~on]))
    if force:
        np.testing.assert_allclose(rec.force, src.force, atol=TOL_FORCE, rtol=0)
    else:
        assert rec.force is None
    np.testing.assert_array_equal(rec.missing, np.zeros(400))
    import h5py

    with h5py.File(out) as f:
        np.testing.assert_allclose(f["robot/clock"][()], src.time, atol=TOL_TIME, rtol=0)
        assert "kept_samples" in f.attrs["serial_summary"]


def test_round_trip_keeps_missing_mask(tmp_path):
    src = builtin_run(2, 1, 200, dt=0.01)
    miss = np.zeros(200, np.uint8)
    miss[[50, 51, 120]] = 1
    src.missing = miss
    src.contact[miss == 1] = 0
    src.normal[miss == 1] = np.nan
    data, _ = emulate_bytes(src)
    out = tmp_path / "rec.h5"
    s = record_stream(FakeStream([data]), out)
    assert (s.missing_samples, s.gaps) == (3, 2)
    np.testing.assert_array_equal(read_run(out).missing, miss)


# ---------------------------------------------------------------------------------
# the read loop: always-valid file, unplug, Ctrl-C, nothing received


def _chunks(n_samples=300, fingers=1, per=10, faults=Faults()):
    run = builtin_run(2, fingers, n_samples, dt=0.01)
    return run, [c for c in _group(iter_chunks(run, faults), per)]


def _group(it, per):
    buf = []
    for c in it:
        buf.append(c)
        if len(buf) == per:
            yield b"".join(buf)
            buf = []
    if buf:
        yield b"".join(buf)


def test_output_is_a_valid_run_at_every_moment_and_unplug_keeps_what_arrived(tmp_path):
    out = tmp_path / "rec.h5"
    src, chunks = _chunks(300, fingers=2, per=5)
    sizes = []

    def check(i):  # before every read: the file is absent (too little yet) or a valid run
        if out.exists():
            sizes.append(read_run(out).n_samples)
        time.sleep(0.02)  # data trickles in: 40 reads take ~0.8 s, snapshots every 0.05 s

    s = record_stream(FakeStream(chunks[:40], end=serial.SerialException("device disconnected"), on_read=check),
                      out, snapshot_interval=0.05)
    assert "link closed" in s.stop_reason and "disconnected" in s.stop_reason
    # grew while recording (>= 2 distinct sizes: a loaded machine may write few snapshots)
    assert len(set(sizes)) >= 2 and sizes == sorted(sizes)
    rec = read_run(out)
    assert rec.n_samples == 200 and s.kept_samples == 200  # 40 chunks of 5 samples
    np.testing.assert_allclose(rec.finger_position, src.finger_position[:200], atol=TOL_POS, rtol=0)
    assert not list(tmp_path.glob(".*part"))  # no temporary file left behind


def test_unplug_through_oserror_eio(tmp_path):
    out = tmp_path / "rec.h5"
    _, chunks = _chunks(50)
    s = record_stream(FakeStream(chunks, end=OSError(5, "Input/output error")), out)
    assert "Input/output error" in s.stop_reason and read_run(out).n_samples == 50


def test_keyboard_interrupt_leaves_a_valid_file(tmp_path, caplog):
    out = tmp_path / "rec.h5"
    src, chunks = _chunks(100, per=10)
    with caplog.at_level(logging.INFO, logger="tacest"):
        s = record_stream(FakeStream(chunks[:7], end=KeyboardInterrupt()), out)
    msgs = [r.getMessage() for r in caplog.records]
    assert s.stop_reason == "interrupted (Ctrl-C)"
    rec = read_run(out)
    assert rec.n_samples == 70
    np.testing.assert_allclose(rec.finger_position, src.finger_position[:70], atol=TOL_POS, rtol=0)
    assert any(m.startswith("kept 70 samples (70 lines), dropped 0 lines") for m in msgs)


def test_duration_stops_recording(tmp_path):
    out = tmp_path / "rec.h5"
    _, chunks = _chunks(100, per=1)
    fs = FakeStream(chunks)
    s = record_stream(fs, out, duration=2.05, clock=lambda: 0.1 * fs.i)  # 0.1 s per read
    assert "duration" in s.stop_reason and s.kept_samples == 21


@pytest.mark.parametrize("data", [b"", b"\xff\xfe garbage\n" * 50, HDR, HDR + stream([0]),
                                  stream(range(20))])  # the last: samples but never a header
def test_nothing_valid_raises_and_writes_no_file(tmp_path, data):
    out = tmp_path / "rec.h5"
    with pytest.raises(TacestError) as exc:
        record_stream(FakeStream([data]), out, name="/dev/fake")
    msg = str(exc.value)
    assert "\n" not in msg and "no run recorded from /dev/fake" in msg and "kept" in msg
    assert not out.exists() and not list(tmp_path.iterdir())


def test_port_that_cannot_be_opened(tmp_path):
    with pytest.raises(TacestError) as exc:
        record_serial("/dev/does-not-exist-tacest", output=tmp_path / "x.h5")
    assert "cannot open serial port /dev/does-not-exist-tacest" in str(exc.value) and "\n" not in str(exc.value)
    assert not (tmp_path / "x.h5").exists()


def test_summary_line_format():
    data = HDR + stream(range(3)) + b"junk\n" + line(4)[:-4] + b"*00\n" + stream(range(5, 7))
    s = assemble(data).summary()
    assert s.line() == ("kept 5 samples (5 lines), dropped 2 lines (checksum 1, malformed 1), "
                        "missing 2 samples in 1 gaps")


def test_header_for_run_matches_format():
    run = builtin_run(3, 2, 10)
    text = format_header(header_for_run(run))
    assert text == "#TACEST,1,dim=3,fingers=2,radius=0.01,dt=0.001"
    assert math.isclose(header_for_run(run).dt, 0.001)


def test_output_folder_vanishing_is_a_one_line_error(tmp_path):
    import shutil

    folder = tmp_path / "sub"
    folder.mkdir()
    out = folder / "rec.h5"
    _, chunks = _chunks(100, per=10)

    def remove(i):
        if i == 5:
            shutil.rmtree(folder)

    # no snapshot before the end (interval 1000 s): the final write finds no folder
    with pytest.raises(TacestError) as exc:
        record_stream(FakeStream(chunks, on_read=remove), out, snapshot_interval=1000.0)
    assert "does not exist" in str(exc.value) and "\n" not in str(exc.value)


def test_write_error_in_the_snapshot_thread_reaches_the_caller(tmp_path, monkeypatch):
    import tacest.sensors.serial_rig as rig

    def broken(run, clock, output):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(rig, "write_snapshot", broken)
    _, chunks = _chunks(100, per=10)
    with pytest.raises(TacestError) as exc:
        record_stream(FakeStream(chunks), tmp_path / "rec.h5", snapshot_interval=0.0)
    assert "cannot write the run file" in str(exc.value) and "No space left" in str(exc.value)


def test_docs_example_session(tmp_path, caplog):
    """The example session of docs/serial_protocol.md §9, line for line."""
    session = (b"S,6,0.06,0,0.1,0.048,0,0,0,,*4E\n"
               b"#TACEST,1,dim=2,fingers=1,radius=0.010,dt=0.01\n"
               b"S,7,0.07,0,0.1,0.05,1,0.5,-0.2,0,1*63\n"
               b"S,8,0.08,0,0.101,0.052,0,0,0,,*7A\n"
               b"S,9,0.09,0,0.102,0.057,0,0,0,,*7F\n"
               b"S,11,0.11,0,0.104,0.058,0,0,0,,*45\n"
               b"#TACEST,1,dim=2,fingers=1,radius=0.010,dt=0.01\n"
               b"S,12,0.12,0,0.105,0.06,1,0.2,-0.9,0.0,1.0*59\n")
    out = tmp_path / "run.h5"
    with caplog.at_level(logging.INFO, logger="tacest"):
        record_stream(FakeStream([session]), out)
    msgs = [r.getMessage() for r in caplog.records]
    assert ("kept 4 samples (4 lines), dropped 2 lines (checksum 1, before header 1), "
            "missing 2 samples in 1 gaps") in msgs
    run = read_run(out)
    np.testing.assert_allclose(run.time, [0, 0.01, 0.02, 0.03, 0.04, 0.05], atol=1e-15)
    np.testing.assert_array_equal(run.missing, [0, 0, 1, 1, 0, 0])
    np.testing.assert_array_equal(run.contact[:, 0], [1, 0, 0, 0, 0, 1])
    np.testing.assert_allclose(run.finger_position[:, 0, 0], [0.1, 0.101, 0.102, 0.103, 0.104, 0.105], atol=1e-12)
    import h5py

    with h5py.File(out) as f:
        np.testing.assert_allclose(f["robot/clock"][()], [0.07, 0.08, np.nan, np.nan, 0.11, 0.12])

"""A device emulator for the tacest serial line protocol, for tests and demos.

It plays a recording (a tacest run file) or a small built-in simulation as the line
protocol of SPEC, optionally with the faults real links show, into a pseudo-terminal
(``os.openpty``), any pyserial URL, or a file::

    python -m tacest.sensors.emulator RUN.h5 --rate 1000 --corrupt 0.01 --drop 0.001 \\
        --garbage 0.001 --repeat-header-every 500 --disconnect-after 20000 --pty
    # prints e.g. /dev/pts/5; then, in another shell:
    tacest record --source serial --port /dev/pts/5 -o out.h5

Library use (no threads, no ptys)::

    data, log = emulate_bytes(run, Faults(corrupt=0.01, seed=1))
    asm = Assembler(); asm.feed(data); asm.finish()

Faults (each a probability per line or per sample, drawn from ``numpy.random`` with a
seed, so a stream is reproducible):

* ``corrupt``: one byte of the line body is replaced by another printable byte, so the
  checksum no longer matches (a single changed byte always changes an XOR checksum);
* ``truncate``: the line is cut at a random point (the newline survives);
* ``garbage``: a line of 1-80 random bytes (any value but ``\\n``, so often not UTF-8)
  is inserted before the line;
* ``drop``: a whole sample (all finger lines of one seq) is never sent (a gap);
* ``drop_line``: one finger line is never sent (an incomplete sample when F > 1);
* ``corrupt_lines``: these (seq, finger) lines are corrupted for sure (as ``corrupt``),
  for tests that need a fault at a known place;
* ``repeat_header_every``: the header is sent again every N sample lines;
* ``disconnect_after``: the link closes after N lines (of any kind) were written.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator, Optional

import numpy as np

from tacest.constants import STANDARD_GRAVITY
from tacest.sensors.serial_protocol import Header, Precision, format_header, format_sample

_PRINTABLE = np.frombuffer(b"0123456789.,-+eE*SABCDFXYZabcdfxyz #", np.uint8)


@dataclass
class Faults:
    """Fault rates (probabilities in [0, 1]) and events; see the module docstring."""

    corrupt: float = 0.0
    truncate: float = 0.0
    garbage: float = 0.0
    drop: float = 0.0
    drop_line: float = 0.0
    repeat_header_every: int = 0
    disconnect_after: Optional[int] = None
    seed: int = 0
    #: (seq, finger) pairs whose lines are always corrupted
    corrupt_lines: frozenset = frozenset()


@dataclass
class FaultLog:
    """What the emulator actually sent.

    intact_lines : S lines sent unharmed; corrupted / truncated / garbage : lines of each
    fault; dropped_samples : seq values never sent; dropped_lines : (seq, finger) of single
    lines never sent; headers : header lines sent; lines_written : all lines;
    disconnected : whether the disconnect-after limit was hit.
    """

    intact_lines: int = 0
    corrupted: int = 0
    truncated: int = 0
    garbage: int = 0
    dropped_samples: list = field(default_factory=list)
    dropped_lines: list = field(default_factory=list)
    headers: int = 0
    lines_written: int = 0
    samples_started: int = 0
    disconnected: bool = False
    #: seq of every S line sent intact, with its finger, in order
    intact: list = field(default_factory=list)


def header_for_run(run) -> Header:
    """The protocol header describing ``run`` (dim, fingers, radii, dt, force, gravity)."""
    return Header(dim=run.dim, fingers=run.n_fingers, radius=tuple(float(r) for r in run.finger_radius),
                  dt=float(run.dt), force=run.force is not None,
                  gravity=tuple(float(g) for g in np.asarray(run.gravity, float)))


def builtin_run(dim: int = 2, fingers: int = 1, samples: int = 2000, dt: float = 0.001):
    """A small deterministic simulated run: fingers circle a fixed disc/sphere
    (radius 0.05 m, centre at height 0.05 m) while their distance oscillates so that they
    touch it about half of the time.

    Returns a :class:`tacest.io.run.Run`: finger_position (T, F, D) m; contact (T, F);
    force (T, F, D) N = 500 N/m × penetration, pushing into the object; normal (T, F, D)
    unit outward, NaN without contact.
    """
    from tacest.io.run import Run

    R, r = 0.05, 0.01
    centre = np.zeros(dim)
    centre[-1] = 0.05
    t = np.arange(samples) * dt
    pos = np.zeros((samples, fingers, dim))
    for f in range(fingers):
        theta = 0.5 * t + 2 * np.pi * f / fingers
        d = R + r + 0.003 * np.sin(2 * np.pi * 0.5 * t + f)  # m: 3 mm in and out
        if dim == 2:
            u = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        else:
            phi = 0.3 * np.sin(0.2 * t)
            u = np.stack([np.cos(theta) * np.cos(phi), np.sin(theta) * np.cos(phi), np.sin(phi)], axis=1)
        pos[:, f] = centre + d[:, None] * u
    rel = pos - centre
    dist = np.linalg.norm(rel, axis=-1)
    contact = (dist <= R + r).astype(np.uint8)
    normal = rel / dist[..., None]
    force = -500.0 * np.maximum(R + r - dist, 0.0)[..., None] * normal
    normal[contact == 0] = np.nan
    g = np.zeros(dim)
    g[-1] = -STANDARD_GRAVITY
    return Run(dim=dim, dt=dt, time=t, gravity=g, source="emulator-builtin", finger_position=pos,
               finger_radius=np.full(fingers, r), contact=contact, force=force, normal=normal)


def iter_chunks(run, faults: Faults = Faults(), precision: Precision = Precision(), start_seq: int = 0,
                log: Optional[FaultLog] = None) -> Iterator[bytes]:
    """Yield the protocol bytes of ``run`` one sample at a time (the header comes with the
    first chunk; a dropped sample yields b"" to keep the pace).

    seq of sample k is ``start_seq + k`` (no wrap: the recorder unwraps uint16/uint32
    counters, pass e.g. ``start_seq=65530`` to test that).  What the run does not know is
    not sent: a finger line marked in ``run.finger_missing_mask`` (per finger, or every
    finger of a ``run.missing`` sample).  ``log`` (a :class:`FaultLog`) is filled as it goes.
    """
    log = FaultLog() if log is None else log
    rng = np.random.default_rng(faults.seed)
    header = (format_header(header_for_run(run)) + "\n").encode("ascii")
    limit = faults.disconnect_after
    F = run.n_fingers
    lines_since_header = 0
    has_force = run.force is not None
    unknown = run.finger_missing_mask  # (T, F) bool
    missing = unknown.all(axis=1)
    corrupt_lines = {(int(q), int(f)) for q, f in faults.corrupt_lines}

    def emit(out: list, line: bytes) -> bool:
        if limit is not None and log.lines_written >= limit:
            log.disconnected = True
            return False
        out.append(line)
        log.lines_written += 1
        return True

    out: list = []
    if not emit(out, header):
        return
    log.headers += 1
    for k in range(run.n_samples):
        seq = start_seq + k
        log.samples_started += 1
        if missing[k] or rng.random() < faults.drop:
            if not missing[k]:
                log.dropped_samples.append(seq)
            yield b"".join(out)
            out = []
            continue
        for f in range(F):
            if faults.repeat_header_every and lines_since_header >= faults.repeat_header_every:
                if not emit(out, header):
                    break
                log.headers += 1
                lines_since_header = 0
            if rng.random() < faults.drop_line:
                log.dropped_lines.append((seq, f))
                continue
            if unknown[k, f]:
                continue
            if rng.random() < faults.garbage:
                n = int(rng.integers(1, 81))
                junk = rng.integers(0, 256, n, dtype=np.uint8)
                junk[junk == 10] = 0xFF  # no newline inside
                junk[0] = 0x80 | (junk[0] & 0x7F)  # at least one non-blank, non-ASCII byte
                if not emit(out, junk.tobytes() + b"\n"):
                    break
                log.garbage += 1
            line = format_sample(seq, float(run.time[k]), f, run.finger_position[k, f], int(run.contact[k, f]),
                                 run.force[k, f] if has_force else None, run.normal[k, f], precision).encode("ascii")
            lines_since_header += 1
            u = rng.random()
            if u < faults.corrupt or (seq, f) in corrupt_lines:
                star = line.rfind(b"*")
                i = int(rng.integers(0, star))
                choices = _PRINTABLE[_PRINTABLE != line[i]]
                line = line[:i] + bytes([int(rng.choice(choices))]) + line[i + 1:]
                kind = "corrupted"
            elif u < faults.corrupt + faults.truncate:
                line = line[: int(rng.integers(1, len(line) - 1))]
                kind = "truncated"
            else:
                kind = "intact"
            if not emit(out, line + b"\n"):
                break
            if kind == "intact":
                log.intact_lines += 1
                log.intact.append((seq, f))
            else:
                setattr(log, kind, getattr(log, kind) + 1)
        yield b"".join(out)
        out = []
        if log.disconnected:
            return


def emulate_bytes(run=None, faults: Faults = Faults(), precision: Precision = Precision(),
                  start_seq: int = 0) -> tuple[bytes, FaultLog]:
    """The whole byte stream for ``run`` (default: :func:`builtin_run`) and its :class:`FaultLog`."""
    run = builtin_run() if run is None else run
    log = FaultLog()
    data = b"".join(iter_chunks(run, faults, precision, start_seq, log))
    return data, log


def play(chunks: Iterator[bytes], write: Callable[[bytes], object], rate: float,
         max_batch: float = 0.005) -> int:
    """Write ``chunks`` (one per sample) through ``write`` at ``rate`` samples/s
    (0: as fast as possible), batching what is due every ``max_batch`` s.  Returns the
    number of bytes written."""
    n_bytes = 0
    if rate <= 0:
        for c in chunks:
            if c:
                write(c)
                n_bytes += len(c)
        return n_bytes
    t0 = time.perf_counter()
    k = 0
    pending = []
    it = iter(chunks)
    done = False
    while not done:
        due = int((time.perf_counter() - t0) * rate) + 1
        while k < due:
            try:
                pending.append(next(it))
            except StopIteration:
                done = True
                break
            k += 1
        if pending:
            data = b"".join(pending)
            pending = []
            if data:
                write(data)
                n_bytes += len(data)
        if not done:
            wake = t0 + k / rate
            time.sleep(max(0.0, min(max_batch, wake - time.perf_counter())))
    return n_bytes


class PtyPort:
    """The master side of a pseudo-terminal; a recorder opens :attr:`name` (the slave).

    ``wait_connected`` blocks until someone opens the slave; ``write`` sends bytes;
    ``close`` first waits until the reader has taken everything (Linux discards unread
    slave input when the master closes), then hangs up: the reader sees EIO, as when a
    USB serial device is unplugged.
    """

    def __init__(self):
        import tty

        self.master, slave = os.openpty()
        self.name = os.ttyname(slave)
        tty.setraw(slave)  # no echo, no line editing, no CR/LF translation
        os.close(slave)
        self._slave = None

    def wait_connected(self, timeout: float = 30.0, settle: float = 0.2) -> bool:
        """Wait until the slave is opened (the master stops reporting POLLHUP), then
        ``settle`` s more (pyserial flushes its input right after opening)."""
        import select

        p = select.poll()
        p.register(self.master, select.POLLHUP)
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if not any(ev & select.POLLHUP for _, ev in p.poll(20)):
                time.sleep(settle)
                # our own handle on the slave, to see how much the reader has not read yet
                self._slave = os.open(self.name, os.O_RDWR | os.O_NOCTTY)
                return True
        return False

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            n = os.write(self.master, view)
            view = view[n:]

    def unread(self) -> int:
        """Bytes the reader has not read yet."""
        import fcntl
        import struct
        import termios

        if self._slave is None:
            return 0
        return struct.unpack("i", fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"))[0]

    def close(self, drain_timeout: float = 5.0) -> None:
        t_end = time.monotonic() + drain_timeout
        quiet = 0
        while time.monotonic() < t_end and quiet < 3:  # 3 readings of 0 in a row, 20 ms apart
            quiet = quiet + 1 if self.unread() == 0 else 0
            time.sleep(0.02)
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None
        os.close(self.master)


def _load_run(path):
    from tacest.io.run import read_run

    return read_run(path)


def main(argv=None) -> int:
    """``python -m tacest.sensors.emulator``: see the module docstring and ``--help``."""
    ap = argparse.ArgumentParser(prog="python -m tacest.sensors.emulator",
                                 description="Play a run file (or a built-in simulation) as the tacest serial "
                                             "line protocol, with optional faults.")
    ap.add_argument("run", nargs="?", help="run file to play (default: built-in simulation)")
    ap.add_argument("--dim", type=int, choices=(2, 3), default=2, help="[built-in] dimension")
    ap.add_argument("--fingers", type=int, default=1, help="[built-in] fingers")
    ap.add_argument("--samples", type=int, default=5000, help="[built-in] samples")
    ap.add_argument("--dt", type=float, default=0.001, help="[built-in] sample period, s")
    ap.add_argument("--rate", type=float, default=None,
                    help="samples per second (default 1/dt; 0 = as fast as possible)")
    ap.add_argument("--corrupt", type=float, default=0.0, help="bad-checksum rate per line")
    ap.add_argument("--truncate", type=float, default=0.0, help="truncated-line rate per line")
    ap.add_argument("--garbage", type=float, default=0.0, help="garbage-line rate per line")
    ap.add_argument("--drop", type=float, default=0.0, help="dropped-sample rate")
    ap.add_argument("--drop-line", type=float, default=0.0, help="dropped single finger line rate")
    ap.add_argument("--repeat-header-every", type=int, default=0, metavar="N", help="repeat the header every N lines")
    ap.add_argument("--disconnect-after", type=int, default=None, metavar="N", help="hang up after N lines")
    ap.add_argument("--start-seq", type=int, default=0, help="seq of the first sample")
    ap.add_argument("--seed", type=int, default=0)
    where = ap.add_mutually_exclusive_group()
    where.add_argument("--pty", action="store_true", help="serve on a new pseudo-terminal (default); prints its path")
    where.add_argument("--url", help="write to this pyserial URL or device")
    where.add_argument("--out", help="write the bytes to this file ('-': stdout)")
    ap.add_argument("--baud", type=int, default=115200, help="[--url] baud rate")
    ap.add_argument("--wait", type=float, default=60.0, help="[--pty] seconds to wait for a reader")
    a = ap.parse_args(argv)

    from tacest.errors import TacestError

    try:
        run = _load_run(a.run) if a.run else builtin_run(a.dim, a.fingers, a.samples, a.dt)
    except TacestError as exc:
        print(f"emulator: error: {exc}", file=sys.stderr)
        return 2
    if run.n_fingers == 0:
        print(f"emulator: error: {a.run}: has no /robot and /tactile to play", file=sys.stderr)
        return 2
    faults = Faults(corrupt=a.corrupt, truncate=a.truncate, garbage=a.garbage, drop=a.drop, drop_line=a.drop_line,
                    repeat_header_every=a.repeat_header_every, disconnect_after=a.disconnect_after, seed=a.seed)
    rate = (1.0 / run.dt) if a.rate is None else a.rate
    log = FaultLog()
    chunks = iter_chunks(run, faults, start_seq=a.start_seq, log=log)
    try:
        if a.out:
            rate = 0.0 if a.rate is None else rate
            if a.out == "-":
                play(chunks, sys.stdout.buffer.write, rate)
                sys.stdout.flush()
            else:
                with open(a.out, "wb") as fh:
                    play(chunks, fh.write, rate)
        elif a.url:
            import serial

            try:
                port = serial.serial_for_url(a.url, baudrate=a.baud)
            except (serial.SerialException, OSError, ValueError) as exc:
                print(f"emulator: error: cannot open {a.url}: {exc}", file=sys.stderr)
                return 2
            try:
                play(chunks, port.write, rate)
                port.flush()
            finally:
                port.close()
        else:
            pty = PtyPort()
            print(pty.name, flush=True)
            print(f"emulator: waiting for a reader on {pty.name}", file=sys.stderr, flush=True)
            if not pty.wait_connected(a.wait):
                print(f"emulator: error: nobody opened {pty.name} within {a.wait:g} s", file=sys.stderr)
                os.close(pty.master)
                return 2
            try:
                play(chunks, pty.write, rate)
            except OSError as exc:  # the reader went away
                print(f"emulator: reader closed the link ({exc})", file=sys.stderr)
            finally:
                pty.close()
    except KeyboardInterrupt:
        print("emulator: interrupted", file=sys.stderr)
    print(f"emulator: wrote {log.lines_written} lines ({log.intact_lines} intact sample lines, "
          f"{log.corrupted} corrupted, {log.truncated} truncated, {log.garbage} garbage, "
          f"{len(log.dropped_samples)} samples dropped, {len(log.dropped_lines)} lines dropped, "
          f"{log.headers} headers)" + (", then hung up" if log.disconnected else ""), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

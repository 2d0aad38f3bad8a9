"""Record a run file from a serial tactile rig (``tacest record --source serial``).

Two layers:

* :class:`Assembler` — pure state machine, no I/O.  Feed it bytes as they arrive
  (:meth:`Assembler.feed`); it splits lines, parses them with
  :mod:`tacest.sensors.serial_protocol`, assembles samples by ``seq``, records gaps, counts
  every dropped line by reason, and builds a SPEC :class:`~tacest.io.run.Run` of what it
  has so far (:meth:`Assembler.to_run`).
* :func:`record_serial` / :func:`record_stream` — the read loop: open the port with
  pyserial (``serial.serial_for_url``: device paths, ``loop://``, ``socket://``, a
  pseudo-terminal), read with a short timeout, feed the assembler, and keep the output
  file a complete, valid run file at every moment by writing atomic snapshots.

Decisions (documented for users in docs/serial_protocol.md):

* time: ``time[k] = k * dt`` with k = seq − (first kept seq); the rig clock ``t`` is kept
  in ``/robot/clock`` (T,) s, NaN where the sample is missing.
* every valid line is kept.  A sample is complete when all F fingers arrived; a finger
  line that is missing or invalid leaves that (sample, finger) unknown:
  ``/quality/missing_finger`` [k, f] = 1 with placeholders for that finger only (position
  linearly interpolated from the finger's own known samples, contact 0, force 0,
  normal NaN), while the sibling fingers' lines of the same sample keep all their values.
  ``/quality/missing`` [k] = 1 where any finger of sample k is unknown (its OR over
  fingers, so a reader that only knows the per-sample mask stays on the safe side).
* gaps (missing seq values) keep uniform time: every finger of the sample is unknown.
* the run spans the first to the last sample of which a line was kept, and is written
  once it has 2 samples and at least one complete one (so every finger has a known
  position to interpolate from).
* seq wrap-around at 2**16 or 2**32 is unwrapped; any other backward jump of more than
  :data:`ORDER_WINDOW` samples is a device restart and ends the run (what came before
  is saved); a forward jump of more than ``max_gap`` seconds ends it too.
* a header with different settings after samples were kept ends the run (saved);
  before any complete sample was kept, the newer header simply wins.
* the output file is rewritten atomically (temp name + rename) every
  ``snapshot_interval`` seconds, or less often when the write itself gets slow (its
  cost grows with the run: the interval is at least ``SNAPSHOT_DUTY`` times the last
  write time), and once at the end.  Writes run on a background thread so reading
  never waits for the disk.  Measured in benchmarks/bench_serial.py; HDF5 SWMR
  appends were rejected because a plain reader cannot open the file while it is being
  written (and a killed writer leaves it marked open).
"""

from __future__ import annotations

import logging

import json
import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from tacest.errors import TacestError
from tacest.interrupt import accept_interrupt
from tacest.sensors.serial_protocol import (
    DROP_REASONS,
    NORMAL_NORM_TOL,
    Header,
    LineError,
    parse_header,
    parse_sample,
)

log = logging.getLogger(__name__)

#: Longest line accepted (bytes, before the newline).  A 3-D line with generous
#: precision is < 150 bytes; anything past this is garbage and is dropped as
#: ``malformed`` without buffering it further.
MAX_LINE = 512

#: A line whose seq is at most this many samples older than the current sample is a
#: late or repeated line (dropped as ``order``); further back is a device restart.
ORDER_WINDOW = 8

#: seq counters that firmware typically wraps (uint16, uint32) and the largest jump
#: across a wrap that is accepted as one (in samples).
WRAP_MODULI = (1 << 16, 1 << 32)
WRAP_WINDOW = 1024

#: Snapshot writes may take at most 1/SNAPSHOT_DUTY of wall time (5 %).
SNAPSHOT_DUTY = 20.0


# ---------------------------------------------------------------------------------
# summary


@dataclass
class RecordSummary:
    """What a recording kept and lost.

    kept_samples : complete samples in the run (every finger arrived);
    kept_lines : valid sample lines in the run (those of complete samples and of
    partial ones); dropped : reason -> lines dropped (reasons of
    serial_protocol.DROP_REASONS); missing_samples / gaps : samples inside the run marked
    in /quality/missing (some finger unknown), and the number of runs of consecutive
    missing samples; partial_samples : those of the missing samples of which some finger
    lines did arrive (kept; the rest is in /quality/missing_finger); headers : valid header lines seen;
    stop_reason : why recording ended; output : the file written (None if none).
    """

    kept_samples: int = 0
    kept_lines: int = 0
    dropped: dict = field(default_factory=lambda: {r: 0 for r in DROP_REASONS})
    missing_samples: int = 0
    gaps: int = 0
    partial_samples: int = 0
    headers: int = 0
    bytes_received: int = 0
    stop_reason: str = ""
    output: Optional[str] = None
    wall_time: float = 0.0
    snapshots: int = 0
    snapshot_time_max: float = 0.0

    #: lines kept from partial samples (set by :meth:`Assembler.summary`)
    partial_lines: int = 0

    @property
    def dropped_lines(self) -> int:
        return int(sum(self.dropped.values()))

    def line(self) -> str:
        """``kept N samples (M lines), dropped D lines (checksum X, ...), missing G samples in H gaps``,
        plus ``(P partial: their Q lines kept)`` when some missing samples arrived in part."""
        parts = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in self.dropped.items() if v)
        dropped = f"dropped {self.dropped_lines} lines" + (f" ({parts})" if parts else "")
        partial = ""
        if self.partial_samples:
            partial = (f" ({self.partial_samples} partial: their {self.partial_lines} "
                       f"line{'s' if self.partial_lines != 1 else ''} kept)")
        return (f"kept {self.kept_samples} samples ({self.kept_lines} lines), {dropped}, "
                f"missing {self.missing_samples} samples in {self.gaps} gaps{partial}")

    __str__ = line

    def as_dict(self) -> dict:
        return {"kept_samples": self.kept_samples, "kept_lines": self.kept_lines,
                "dropped_lines": self.dropped_lines, "dropped": dict(self.dropped),
                "missing_samples": self.missing_samples, "gaps": self.gaps,
                "partial_samples": self.partial_samples, "partial_lines": self.partial_lines,
                "headers": self.headers,
                "bytes_received": self.bytes_received, "stop_reason": self.stop_reason}


# ---------------------------------------------------------------------------------
# the assembler


class Assembler:
    """Turn a byte stream of the serial protocol into samples.

    Parameters
    ----------
    normal_tol : relative tolerance on |n| - 1 before a contact normal is dropped
        (see serial_protocol.NORMAL_NORM_TOL).
    max_gap : float, s: a forward seq jump longer than this ends the run (a corrupted
        seq or a device that silently restarted far ahead; also bounds memory).

    Storage is indexed by k = unwrapped seq − first seq seen; arrays grow by doubling.
    Per sample k and finger f: ``got[k, f]`` (line arrived), ``pos`` (m), ``contact``,
    ``force`` (N), ``normal``, and ``clock[k]`` (rig time of the first line, s).
    """

    def __init__(self, normal_tol: float = NORMAL_NORM_TOL, max_gap: float = 60.0):
        self.normal_tol = normal_tol
        self.max_gap = max_gap
        self.header: Optional[Header] = None
        self.header_line: Optional[str] = None
        self.dropped = {r: 0 for r in DROP_REASONS}
        self.headers = 0
        self.bytes_received = 0
        self.stop_reason: Optional[str] = None  # set when the stream cannot go on into this run
        self.messages: list[str] = []  # notable events, for the user
        self._buf = b""
        self._skipping = False  # inside an over-long line
        self._reset_samples()

    # -- storage -----------------------------------------------------------------
    def _reset_samples(self):
        self._seq0 = None      # unwrapped seq of index 0
        self._wrap = 0         # offset added to raw seq (multiples of a wrap modulus)
        self._cur = -1         # index of the newest sample seen
        self._cap = 0
        self._n_complete = 0   # samples of which every finger arrived
        self._n_lines = 0      # sample lines stored
        self._first = -1       # index of the first sample with a stored line
        self._last = -1        # index of the newest sample with a stored line
        self.version = 0       # increments whenever kept data changes (for snapshots)

    def _alloc(self, cap):
        h = self.header
        F, D = h.fingers, h.dim
        new = {
            "got": np.zeros((cap, F), bool),
            "pos": np.full((cap, F, D), np.nan),
            "contact": np.zeros((cap, F), np.uint8),
            "force": np.zeros((cap, F, D)),
            "normal": np.full((cap, F, D), np.nan),
            "clock": np.full((cap,), np.nan),
        }
        if self._cap:
            for k, arr in new.items():
                arr[: self._cap] = getattr(self, "_" + k)
        for k, arr in new.items():
            setattr(self, "_" + k, arr)
        self._cap = cap

    # -- public state --------------------------------------------------------------
    @property
    def kept_samples(self) -> int:
        return self._n_complete

    @property
    def stopped(self) -> bool:
        return self.stop_reason is not None

    def _drop(self, reason):
        self.dropped[reason] += 1

    # -- input -----------------------------------------------------------------------
    def feed(self, data: bytes) -> None:
        """Process received bytes (any chunking).  After :attr:`stopped` turns True the
        rest is ignored."""
        if self.stopped or not data:
            return
        self.bytes_received += len(data)
        buf = self._buf + data
        lines = buf.split(b"\n")
        self._buf = lines.pop()
        for raw in lines:
            if self._skipping:  # tail of an over-long line
                self._skipping = False
                continue
            self._line(raw)
            if self.stopped:
                self._buf = b""
                return
        if len(self._buf) > MAX_LINE:
            self._drop("malformed")
            self._buf = b""
            self._skipping = True

    def flush(self) -> None:
        """End of stream: a final line without its newline is processed as a line
        (it can only pass if it is complete, checksum included)."""
        if self._buf and not self._skipping and not self.stopped:
            self._line(self._buf)
        self._buf = b""

    def _line(self, raw: bytes) -> None:
        line = raw.strip()
        if not line:
            return  # blank lines (e.g. \r\n\r\n) are not counted
        try:
            self._parse(line)
            return
        except LineError as exc:
            error = exc
        # resynchronise: a line glued after garbage or after a truncated line still
        # parses from its own start ('S,' and '#TACEST' occur nowhere else in a valid line)
        start = max(line.rfind(b"S,"), line.rfind(b"#TACEST"))
        if start > 0:
            try:
                self._parse(line[start:])
            except LineError:
                pass
            else:
                self._drop("malformed")  # the junk in front of it
                return
        self._drop(error.reason)

    def _parse(self, line: bytes) -> None:
        if line.startswith(b"#"):
            if not line[:7].upper() == b"#TACEST":
                raise LineError("malformed", "unknown # line")
            self._header(parse_header(line), line)
            return
        if not line.startswith(b"S"):
            raise LineError("malformed", "unknown line type")
        if self.header is None:
            raise LineError("before_header")
        self._sample(parse_sample(line, self.header, self.normal_tol))

    def _header(self, h: Header, line: bytes) -> None:
        self.headers += 1
        if self.header is None:
            self.header, self.header_line = h, line.decode("ascii")
            return
        if h.same_settings(self.header):
            return
        if self._n_complete == 0:
            # nothing kept yet: the newer settings win, partial data under the old ones is dropped
            self.dropped["incomplete"] += int(self._got[: self._cur + 1].sum()) if self._cap else 0
            self.messages.append(f"header changed before any complete sample was kept: now {h.describe()}")
            self.header, self.header_line = h, line.decode("ascii")
            self._reset_samples()
            return
        self.stop_reason = (f"device settings changed mid-run (was {self.header.describe()}; "
                            f"now {h.describe()}): stopped; record again for the new settings")

    def _sample(self, s) -> None:
        h = self.header
        if self._seq0 is None:
            self._seq0 = s.seq
            self._alloc(1024)
        u = s.seq + self._wrap - self._seq0
        if u < self._cur:
            # wrap-around of a uint16/uint32 counter?
            raw_cur = self._cur + self._seq0 - self._wrap
            for m in WRAP_MODULI:
                if raw_cur < m and 0 < s.seq + m - raw_cur <= WRAP_WINDOW:
                    self._wrap += m
                    u = s.seq + self._wrap - self._seq0
                    break
            else:
                if self._cur - u <= ORDER_WINDOW:
                    raise LineError("order", f"seq {s.seq} is older than the current sample")
                self.stop_reason = (f"device restarted (seq went back from {raw_cur} to {s.seq}): "
                                    "stopped; what came before is saved")
                return
        if u > self._cur + 1 + self.max_gap / h.dt:
            raw_cur = self._cur + self._seq0 - self._wrap
            self.stop_reason = (f"seq jumped from {raw_cur} to {s.seq} (more than {self.max_gap:g} s): "
                                "stopped; what came before is saved")
            return
        if u >= self._cap:
            cap = self._cap
            while cap <= u:
                cap *= 2
            self._alloc(cap)
        if u > self._cur:
            self._cur = u
        f = s.finger
        if self._got[u, f]:
            raise LineError("order", f"finger {f} twice in seq {s.seq}")
        self._got[u, f] = True
        self._pos[u, f] = s.position
        self._contact[u, f] = s.contact
        if h.force:
            self._force[u, f] = s.force
        self._normal[u, f] = s.normal
        if math.isnan(self._clock[u]):
            self._clock[u] = s.t
        self._n_lines += 1
        if self._first < 0:
            self._first = u
        self._last = u  # lines never go back to an older sample (see above)
        if self._got[u].all():
            self._n_complete += 1
        self.version += 1

    def finish(self) -> None:
        """End of input: flush the partial line."""
        self.flush()

    # -- output ----------------------------------------------------------------------
    def summary(self) -> RecordSummary:
        """Counts so far (see :class:`RecordSummary`)."""
        s = RecordSummary(dropped=dict(self.dropped), headers=self.headers, bytes_received=self.bytes_received)
        s.kept_samples = self._n_complete
        if self._n_complete:  # only then is there a run (see to_run)
            s.kept_lines = self._n_lines
            got = self._got[self._first:self._last + 1]
            n_got = got.sum(axis=1)
            miss = n_got < self.header.fingers
            s.missing_samples = int(miss.sum())
            s.gaps = int(np.count_nonzero(miss[1:] & ~miss[:-1]) + miss[0])
            s.partial_samples = int(np.count_nonzero(miss & (n_got > 0)))
            s.partial_lines = int(n_got[miss].sum())
        return s

    def to_run(self, extra_attrs: Optional[dict] = None):
        """The run so far, or None before it has 2 samples and a complete one.

        The run spans the first to the last sample of which a line was kept.  A
        (sample, finger) whose line did not arrive is marked in ``missing_finger`` and
        holds placeholders: position linearly interpolated from that finger's known
        samples (held constant before the first and after the last), contact 0, force 0,
        normal NaN.  Returns (Run, clock) where clock is (T,) float, s, the rig clock of
        the first line of each sample (NaN where no line of the sample arrived).
        """
        from tacest.io.run import Run

        if self._n_complete < 1 or self._last - self._first < 1:
            return None
        h = self.header
        i0, i1 = self._first, self._last
        sl = slice(i0, i1 + 1)
        T = i1 - i0 + 1
        got = self._got[sl]
        unknown = ~got  # (T, F)
        pos = self._pos[sl].copy()
        if unknown.any():
            idx = np.arange(T)
            for f in range(h.fingers):
                known = got[:, f]  # not empty: the run has a complete sample
                if not known.all():
                    for d in range(h.dim):
                        pos[~known, f, d] = np.interp(idx[~known], idx[known], pos[known, f, d])
        contact = self._contact[sl].copy()
        contact[unknown] = 0
        normal = self._normal[sl].copy()
        normal[unknown] = np.nan
        normal[contact == 0] = np.nan
        force = None
        if h.force:
            force = self._force[sl].copy()
            force[unknown] = 0.0
        clock = self._clock[sl].copy()
        clock[~got.any(axis=1)] = np.nan
        attrs = {"serial_header": self.header_line or "",
                 "serial_summary": json.dumps(self.summary().as_dict(), sort_keys=True)}
        if extra_attrs:
            attrs.update(extra_attrs)
        run = Run(dim=h.dim, dt=h.dt, time=np.arange(T) * h.dt, gravity=h.gravity_array, source="serial",
                  finger_position=pos, finger_radius=h.radius_array, contact=contact, force=force,
                  normal=normal, missing=unknown.any(axis=1).astype(np.uint8),
                  missing_finger=unknown.astype(np.uint8), extra_attrs=attrs)
        return run, clock


# ---------------------------------------------------------------------------------
# writing


def write_snapshot(run, clock, output) -> None:
    """Validate ``run`` and write it atomically to ``output`` with ``/robot/clock``
    (T,) float, s (rig clock, NaN where the sample is missing)."""
    from tacest.io.h5util import atomic_h5
    from tacest.io.run import fill_run_file

    run.validate(output)
    with atomic_h5(output) as f:
        fill_run_file(f, run)
        d = f["robot"].create_dataset("clock", data=np.asarray(clock, float))
        d.attrs["units"] = "s"
        d.attrs["meaning"] = "rig clock t of each sample as sent by the device; NaN where no line of the sample arrived"


# ---------------------------------------------------------------------------------
# the read loop


def open_port(port: str, baud: int = 115200, timeout: float = 0.05):
    """Open ``port`` (device path or any pyserial URL) for reading; TacestError if it cannot."""
    import serial

    try:
        return serial.serial_for_url(port, baudrate=baud, timeout=timeout)
    except (serial.SerialException, OSError, ValueError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__
        raise TacestError(f"cannot open serial port {port}: {msg}") from None


def record_serial(port, baud: int = 115200, duration: Optional[float] = None, output=None, *,
                  read_timeout: float = 0.05, snapshot_interval: float = 0.25, normal_tol: float = NORMAL_NORM_TOL, max_gap: float = 60.0) -> RecordSummary:
    """Record the serial protocol from ``port`` into the run file ``output``.

    Parameters
    ----------
    port : str (device path or pyserial URL: ``/dev/ttyACM0``, ``/dev/pts/3``,
        ``loop://``, ``socket://host:port`` ...) or an already open serial-like object
        (with ``read(n)``; ``in_waiting`` and ``close()`` used when present).
    baud : int, bits/s (ignored by pseudo-terminals and USB CDC devices).
    duration : float, s of wall time, or None: until the link closes or Ctrl-C.
    output : path of the run file; it is a complete, valid run file from the moment
        2 samples are kept, updated at least every ``snapshot_interval`` s.
    Progress and the final summary go to the module's logger.

    Returns the :class:`RecordSummary`.  Ctrl-C (KeyboardInterrupt) and a lost link end
    the recording normally.  Raises TacestError when the port cannot be opened or when
    fewer than 2 samples were kept (then no file is written).
    """
    if output is None:
        raise TacestError("record_serial needs an output file")
    name = port if isinstance(port, str) else getattr(port, "name", None) or repr(port)
    stream = open_port(port, baud, read_timeout) if isinstance(port, str) else port
    try:
        return record_stream(stream, output, duration=duration, name=name,
                             snapshot_interval=snapshot_interval, normal_tol=normal_tol, max_gap=max_gap)
    finally:
        close = getattr(stream, "close", None)
        if close is not None and isinstance(port, str):
            try:
                close()
            except Exception:  # closing a vanished device may fail; nothing left to save
                pass


class SnapshotWriter:
    """Writes snapshots of the run on a background thread, so the read loop keeps
    draining the port while HDF5 writes (h5py and numpy release the GIL for the bulk of
    the work: measured, the reading thread is never held up more than ~15 ms by a
    0.4 s write of a 1e6-sample run).  One write at a time; an error in the thread is
    raised again by :meth:`check` / :meth:`wait`.
    """

    def __init__(self, output):
        self.output = output
        self._thread = None
        self._error = None
        self.count = 0
        self.last_cost = 0.0  # s
        self.max_cost = 0.0   # s

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def submit(self, run, clock) -> None:
        import threading

        self.wait()
        self._thread = threading.Thread(target=self._write, args=(run, clock), name="tacest-snapshot")
        self._thread.start()

    def write_now(self, run, clock) -> None:
        self.wait()
        self._write(run, clock)
        self.check()

    def _write(self, run, clock):
        t0 = _time.perf_counter()
        try:
            write_snapshot(run, clock, self.output)
        except OSError as exc:  # disk full, folder removed ...: not a link problem
            self._error = TacestError(f"{self.output}: cannot write the run file ({exc})")
            return
        except BaseException as exc:  # handed to the main thread
            self._error = exc
            return
        cost = _time.perf_counter() - t0
        self.count += 1
        if self.count > 1:  # the first write pays for lazy HDF5 set-up (~50 ms): not a trend
            self.last_cost = cost
        self.max_cost = max(self.max_cost, cost)

    def check(self) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            raise err

    def wait(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.check()


def record_stream(stream, output, duration: Optional[float] = None, name: str = "",
                  snapshot_interval: float = 0.25, normal_tol: float = NORMAL_NORM_TOL,
                  max_gap: float = 60.0, clock: Callable[[], float] = _time.monotonic) -> RecordSummary:
    """The read loop of :func:`record_serial` on an open stream (see there).

    ``stream.read(n)`` returns bytes (possibly empty after its timeout) and raises
    ``serial.SerialException`` / ``OSError`` / ``EOFError`` when the link is gone; a
    stream without ``in_waiting`` (a plain file-like object) ends at its first b"".
    ``clock`` is the wall clock for ``duration`` and the snapshot schedule (s).
    """
    import serial

    import tacest.io.run  # noqa: F401  (import h5py and the writer before data flows)

    output = Path(output)
    if not (output.parent if str(output.parent) else Path(".")).is_dir():
        raise TacestError(f"{output}: folder {output.parent} does not exist")
    asm = Assembler(normal_tol=normal_tol, max_gap=max_gap)
    attrs = {"serial_port": str(name)}
    writer = SnapshotWriter(output)
    t_start = clock()
    written_version = -1
    next_snapshot = t_start + snapshot_interval
    header_announced = None
    reason = "end of input"
    log.info(f"recording from {name}" + (f" for {duration:g} s" if duration else " (Ctrl-C to stop)"))

    has_in_waiting = hasattr(stream, "in_waiting")
    try:
        while True:
            if duration is not None and clock() - t_start >= duration:
                reason = f"duration of {duration:g} s reached"
                break
            n = stream.in_waiting if has_in_waiting else 0
            data = stream.read(n if n > 0 else 1)
            if data is None:  # a non-blocking stream with nothing to give
                data = b""
            if data == b"" and not has_in_waiting:  # a plain stream at EOF (pyserial returns b"" on timeout)
                reason = "end of input"
                break
            asm.feed(bytes(data))
            if asm.header is not None and asm.header_line != header_announced:
                header_announced = asm.header_line
                log.info(f"header: {asm.header.describe()}")
            if asm.stopped:
                reason = asm.stop_reason
                break
            now = clock()
            if now >= next_snapshot and not writer.busy:
                writer.check()
                if asm.version != written_version:
                    built = asm.to_run(attrs)
                    if built is not None:
                        writer.submit(*built)
                        written_version = asm.version
                next_snapshot = now + max(snapshot_interval, SNAPSHOT_DUTY * writer.last_cost)
    except KeyboardInterrupt:
        accept_interrupt()  # Ctrl-C ends the recording; what arrived is kept (tacest.interrupt)
        reason = "interrupted (Ctrl-C)"
    except (serial.SerialException, OSError, EOFError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__
        reason = f"link closed ({msg})"
    asm.finish()
    summary = asm.summary()
    summary.stop_reason = reason
    summary.wall_time = clock() - t_start
    attrs["serial_stop_reason"] = reason
    built = asm.to_run(attrs)
    if built is None:
        writer.wait()
        detail = summary.line()
        if asm.header is None:
            detail += "; no valid #TACEST header arrived"
        raise TacestError(f"no run recorded from {name} ({reason}): {detail}")
    writer.write_now(*built)  # always: the final state, with summary and stop reason attrs
    summary.output = str(output)
    summary.snapshots, summary.snapshot_time_max = writer.count, writer.max_cost
    for m in asm.messages:
        log.info(m)
    log.info(f"stopped: {reason}")
    log.info(summary.line())
    log.info(f"wrote {output}: {summary.kept_samples + summary.missing_samples} samples, "
             f"{asm.header.fingers} finger(s), dt = {asm.header.dt:g} s")
    return summary

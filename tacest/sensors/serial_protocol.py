"""The tacest serial line protocol (SPEC "Serial line protocol", docs/serial_protocol.md).

Pure functions, no I/O: checksum, parse and format of header and sample lines.
The recorder (:mod:`tacest.sensors.serial_rig`) and the device emulator
(:mod:`tacest.sensors.emulator`) are both built on this module, so what one writes the
other reads.

Grammar (ASCII, one line per ``\\n``; a trailing ``\\r`` and blanks are ignored)::

    header  #TACEST,1,dim=2,fingers=1,radius=0.010,dt=0.01[,key=value...][*CS]
    sample  S,<seq>,<t>,<finger>,<x>,<y>[,<z>],<contact>,<fx>,<fy>[,<fz>],<nx>,<ny>[,<nz>]*CS

``CS`` is two hex digits: the XOR of every byte from the leading ``S`` (or ``#``) up to,
not including, ``*`` (NMEA 0183 style, but the leading character is included).
A sample line has ``3*D + 5`` comma-separated fields (11 in 2-D, 14 in 3-D).

Units: position m (world frame), rig clock ``t`` s, force N (what the finger exerts ON
the object, world frame), normal unit vector (outward object normal, world frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import reduce
from operator import xor
from typing import Optional

import numpy as np

from tacest.constants import STANDARD_GRAVITY

#: Protocol version this module reads and writes.
PROTOCOL_VERSION = 1

#: A contact normal whose norm is within this relative distance of 1 is renormalised;
#: a worse one is dropped (reason ``normal``).  Firmware that rounds each component to
#: 3 decimals is off by at most sqrt(3) * 0.0005 < 1e-3; 5 % accepts any honest
#: rounding or float16 encoding while still catching a normal that is plainly not unit
#: (a bug, an unscaled force vector, a corrupted digit that slipped past the checksum).
NORMAL_NORM_TOL = 0.05

#: Drop reasons, in the order the recorder reports them.
DROP_REASONS = (
    "checksum",       # *CS present but does not match
    "malformed",      # not a line of the grammar: no *CS, unknown line type, garbage, non-ASCII, too long
    "fields",         # wrong number of comma-separated fields for the header's dim
    "number",         # unparsable or out-of-domain number (NaN/inf position, contact not 0/1, seq < 0 ...)
    "normal",         # contact = 1 with an empty, NaN or non-unit normal
    "finger",         # finger index outside [0, fingers)
    "order",          # seq older than the current sample, or the same finger twice in one sample
    "incomplete",     # a line of a sample not yet complete when new settings replaced the header (none kept yet)
    "before_header",  # sample line before the first valid header
    "header",         # a header line that could not be used (syntax, unsupported version, bad value)
)


class LineError(ValueError):
    """A line that cannot be used; ``reason`` is one of :data:`DROP_REASONS`."""

    def __init__(self, reason: str, detail: str = ""):
        assert reason in DROP_REASONS, reason
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


# ---------------------------------------------------------------------------------
# checksum


def checksum(body: bytes) -> int:
    """XOR of every byte of ``body`` (the line from ``S``/``#`` up to, not including, ``*``).

    >>> checksum(b"S,1")   # 0x53 ^ 0x2C ^ 0x31
    78
    """
    return reduce(xor, body, 0)


def with_checksum(body: str) -> str:
    """``body`` + ``*`` + two upper-case hex digits of :func:`checksum` (no newline)."""
    return f"{body}*{checksum(body.encode('ascii')):02X}"


def split_checksum(line: bytes) -> tuple[bytes, Optional[int]]:
    """Split a stripped line into (body, checksum value or None when there is no ``*CS``).

    Raises LineError("malformed") when a ``*`` is followed by something other than
    exactly two hex digits.
    """
    star = line.rfind(b"*")
    if star < 0:
        return line, None
    tail = line[star + 1:]
    if len(tail) != 2:
        raise LineError("malformed", "checksum must be two hex digits after '*'")
    try:
        value = int(tail, 16)
    except ValueError:
        raise LineError("malformed", "checksum is not hex") from None
    return line[:star], value


# ---------------------------------------------------------------------------------
# header


@dataclass(frozen=True)
class Header:
    """Settings announced by a ``#TACEST`` line.

    dim : 2 or 3; fingers : F >= 1; radius : (F,) float, m; dt : float, s (> 0);
    force : whether the rig measures force (``force=0`` in the header: contact and normal
    only, the force fields are ignored and may be empty); gravity : (D,) m/s²
    (default -STANDARD_GRAVITY along the last axis); extras : other ``key=value`` pairs, kept as text.
    """

    dim: int
    fingers: int
    radius: tuple
    dt: float
    force: bool = True
    gravity: tuple = ()
    version: int = PROTOCOL_VERSION
    extras: dict = field(default_factory=dict, compare=False)

    @property
    def n_fields(self) -> int:
        """Comma-separated fields of a sample line: S, seq, t, finger, D pos, contact, D force, D normal."""
        return 3 * self.dim + 5

    @property
    def radius_array(self) -> np.ndarray:
        """(F,) float, m."""
        return np.asarray(self.radius, float)

    @property
    def gravity_array(self) -> np.ndarray:
        """(D,) float, m/s²."""
        return np.asarray(self.gravity, float)

    def same_settings(self, other: "Header") -> bool:
        """True when ``other`` describes the same stream (extras are not compared).

        Floats compare with a relative tolerance of 1e-9: both sides parse the same
        decimal text, so any real difference is far larger.
        """
        def close(a, b):
            return len(a) == len(b) and all(math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-15) for x, y in zip(a, b))

        return (self.version == other.version and self.dim == other.dim and self.fingers == other.fingers
                and self.force == other.force and close(self.radius, other.radius)
                and close((self.dt,), (other.dt,)) and close(self.gravity, other.gravity))

    def describe(self) -> str:
        """One-line human summary, e.g. ``dim=2, fingers=1, radius=0.01 m, dt=0.01 s``."""
        rad = ",".join(f"{r:g}" for r in self.radius) if len(set(self.radius)) > 1 else f"{self.radius[0]:g}"
        return (f"dim={self.dim}, fingers={self.fingers}, radius={rad} m, dt={self.dt:g} s"
                + ("" if self.force else ", no force"))


def _split_top_level(text: str) -> list[str]:
    """Split on commas that are not inside [...] or (...)."""
    out, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        if ch in "[(":
            depth += 1
        elif ch in "])":
            depth = max(0, depth - 1)
        elif ch == "," and depth == 0:
            out.append(text[start:i])
            start = i + 1
    out.append(text[start:])
    return out


def _number_list(value: str) -> list[float]:
    """Numbers in ``0.01``, ``0.01;0.012``, ``0.01|0.012``, ``0.01 0.012``, ``[0.01,0.012]``."""
    v = value.strip().strip("[]()")
    for sep in ";|, \t":
        v = v.replace(sep, " ")
    parts = v.split()
    if not parts:
        raise ValueError("empty")
    return [float(p) for p in parts]


def parse_header(line: bytes) -> Header:
    """Parse a ``#TACEST`` line (stripped, without the newline).

    Liberal: keys are case-insensitive, blanks around fields are ignored, an optional
    trailing ``*CS`` is checked when present, ``fingers`` defaults to the number of
    radii given, ``radius`` may be one value for every finger or one per finger
    (``radius=0.01;0.012``, ``|`` or blanks, or ``[0.01,0.012]``), unknown keys are kept
    in ``extras``.  Strict: version must be 1; dim 2 or 3; fingers >= 1; dt and radii
    finite and > 0; 1 or F radii.

    Raises LineError("checksum" | "header" | "malformed").
    """
    body, cs = split_checksum(line)
    if cs is not None and checksum(body) != cs:
        raise LineError("checksum", "header checksum does not match")
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise LineError("malformed", "non-ASCII bytes in header") from None
    fields = [f.strip() for f in _split_top_level(text)]
    if fields[0].upper() != "#TACEST":
        raise LineError("malformed", "not a #TACEST header")
    if len(fields) < 2:
        raise LineError("header", "no protocol version")
    try:
        version = int(fields[1])
    except ValueError:
        raise LineError("header", f"protocol version {fields[1]!r} is not an integer") from None
    if version != PROTOCOL_VERSION:
        raise LineError("header", f"protocol version {version} is not supported (this tacest reads {PROTOCOL_VERSION})")
    kv = {}
    for f in fields[2:]:
        if not f:
            continue
        if "=" not in f:
            raise LineError("header", f"field {f!r} is not key=value")
        k, v = f.split("=", 1)
        kv[k.strip().lower()] = v.strip()
    for key in ("dim", "dt", "radius"):
        if key not in kv:
            raise LineError("header", f"missing {key}=")
    try:
        dim = int(kv.pop("dim"))
        dt = float(kv.pop("dt"))
        radius = _number_list(kv.pop("radius"))
        fingers = int(kv.pop("fingers")) if "fingers" in kv else len(radius)
        force_txt = kv.pop("force", "1").lower()
        gravity = _number_list(kv.pop("gravity")) if "gravity" in kv else None
    except ValueError as exc:
        raise LineError("header", f"bad value ({exc})") from None
    if dim not in (2, 3):
        raise LineError("header", f"dim must be 2 or 3, got {dim}")
    if fingers < 1:
        raise LineError("header", f"fingers must be >= 1, got {fingers}")
    if not (math.isfinite(dt) and dt > 0):
        raise LineError("header", f"dt must be > 0, got {dt}")
    if len(radius) == 1:
        radius = radius * fingers
    if len(radius) != fingers:
        raise LineError("header", f"{len(radius)} radii for {fingers} fingers")
    if not all(math.isfinite(r) and r > 0 for r in radius):
        raise LineError("header", "radii must be > 0")
    if force_txt not in ("0", "1", "yes", "no", "true", "false"):
        raise LineError("header", f"force must be 0 or 1, got {force_txt!r}")
    force = force_txt in ("1", "yes", "true")
    if gravity is None:
        gravity = [0.0] * (dim - 1) + [-STANDARD_GRAVITY]
    if len(gravity) != dim or not all(math.isfinite(g) for g in gravity):
        raise LineError("header", f"gravity needs {dim} finite numbers")
    return Header(dim=dim, fingers=fingers, radius=tuple(radius), dt=dt, force=force,
                  gravity=tuple(gravity), version=version, extras=kv)


def format_header(header: Header, checksum_suffix: bool = False) -> str:
    """The header line for ``header`` (no newline).  Radii are written once when all equal,
    else ``;``-separated; ``force=0`` and ``gravity=`` only when not the defaults."""
    rad = header.radius
    rad_txt = f"{rad[0]:.6g}" if len(set(rad)) == 1 else ";".join(f"{r:.6g}" for r in rad)
    parts = ["#TACEST", str(header.version), f"dim={header.dim}", f"fingers={header.fingers}",
             f"radius={rad_txt}", f"dt={header.dt:.9g}"]
    if not header.force:
        parts.append("force=0")
    default_g = tuple([0.0] * (header.dim - 1) + [-STANDARD_GRAVITY])
    if header.gravity and tuple(header.gravity) != default_g:
        parts.append("gravity=" + ";".join(f"{g:.6g}" for g in header.gravity))
    for k, v in header.extras.items():
        parts.append(f"{k}={v}")
    body = ",".join(parts)
    return with_checksum(body) if checksum_suffix else body


# ---------------------------------------------------------------------------------
# sample lines


@dataclass
class SampleLine:
    """One finger of one sample.

    seq : int >= 0; t : rig clock, s (NaN when the field was empty);
    finger : int in [0, F); position : (D,) m; contact : 0 or 1;
    force : (D,) N (NaN when the header says ``force=0``);
    normal : (D,) unit vector, renormalised; NaN where contact = 0.
    """

    seq: int
    t: float
    finger: int
    position: tuple
    contact: int
    force: tuple
    normal: tuple


_NAN3 = (math.nan, math.nan, math.nan)


def _finite(text: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise LineError("number", f"{what} {text!r} is not a number") from None
    if not math.isfinite(v):
        raise LineError("number", f"{what} must be finite")
    return v


def parse_sample(line: bytes, header: Header, normal_tol: float = NORMAL_NORM_TOL) -> SampleLine:
    """Parse and check one ``S`` line (stripped, without the newline) against ``header``.

    Checks, in this order (the first failure is the reason): checksum present and
    matching; ASCII; field count ``3*D + 5``; seq a non-negative integer; t a number
    (empty or NaN allowed: clock unknown); finger an integer in [0, F); position finite;
    contact 0 or 1; force finite (unless ``header.force`` is False: then ignored);
    normal: where contact = 1 finite with | |n| - 1 | <= ``normal_tol`` (renormalised),
    where contact = 0 ignored and returned as NaN.

    Raises LineError with the reason; returns a :class:`SampleLine`.
    """
    body, cs = split_checksum(line)
    if cs is None:
        raise LineError("malformed", "no *CS checksum (truncated line?)")
    if checksum(body) != cs:
        raise LineError("checksum", f"computed {checksum(body):02X}, line says {cs:02X}")
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise LineError("malformed", "non-ASCII bytes") from None
    f = text.split(",")
    D = header.dim
    if f[0].strip() != "S":
        raise LineError("malformed", "not an S line")
    if len(f) != header.n_fields:
        raise LineError("fields", f"{len(f)} fields, dim={D} needs {header.n_fields}")
    try:
        seq = int(f[1])
    except ValueError:
        raise LineError("number", f"seq {f[1]!r} is not an integer") from None
    if seq < 0:
        raise LineError("number", "seq must be >= 0")
    t_txt = f[2].strip()
    if t_txt:
        try:
            t = float(t_txt)
        except ValueError:
            raise LineError("number", f"t {t_txt!r} is not a number") from None
        if math.isinf(t):
            raise LineError("number", "t is infinite")
    else:
        t = math.nan
    try:
        finger = int(f[3])
    except ValueError:
        raise LineError("number", f"finger {f[3]!r} is not an integer") from None
    if not 0 <= finger < header.fingers:
        raise LineError("finger", f"finger {finger} not in [0, {header.fingers})")
    pos = tuple(_finite(x, "position") for x in f[4:4 + D])
    c_txt = f[4 + D].strip()
    if c_txt in ("0", "1"):
        contact = int(c_txt)
    else:
        try:
            cv = float(c_txt)
        except ValueError:
            cv = math.nan
        if cv not in (0.0, 1.0):
            raise LineError("number", f"contact {c_txt!r} is not 0 or 1")
        contact = int(cv)
    if header.force:
        force = tuple(_finite(x, "force") for x in f[5 + D:5 + 2 * D])
    else:
        force = _NAN3[:D]
    if contact:
        n_txt = f[5 + 2 * D:5 + 3 * D]
        try:
            n = [float(x) for x in n_txt]
        except ValueError:
            raise LineError("normal", "contact = 1 needs a normal") from None
        norm = math.sqrt(sum(x * x for x in n))
        if not math.isfinite(norm) or abs(norm - 1.0) > normal_tol:
            raise LineError("normal", f"|n| = {norm:.4g} is not 1 (tolerance {normal_tol})")
        normal = tuple(x / norm for x in n)
    else:
        normal = _NAN3[:D]
    return SampleLine(seq=seq, t=t, finger=finger, position=pos, contact=contact, force=force, normal=normal)


@dataclass(frozen=True)
class Precision:
    """Decimals written by :func:`format_sample`; the round-trip tolerances follow from them
    (half a unit in the last place).  Defaults: t 1 µs, position 1 µm, force 0.1 mN,
    normal 1e-5 (|n| - 1 stays below 1e-4, far inside the 1e-3 the run validator allows)."""

    t: int = 6
    position: int = 6
    force: int = 4
    normal: int = 5


def format_sample(seq: int, t: float, finger: int, position, contact: int, force=None, normal=None,
                  precision: Precision = Precision()) -> str:
    """One ``S`` line with its checksum (no newline).

    position : (D,) m; force : (D,) N or None (fields left empty: a ``force=0`` rig);
    normal : (D,) or None; written only where contact = 1 (empty fields otherwise, as
    SPEC allows).  ``t`` NaN is written as an empty field.
    """
    D = len(position)
    p = precision
    parts = ["S", str(int(seq)), "" if not math.isfinite(t) else f"{t:.{p.t}f}", str(int(finger))]
    parts += [f"{x:.{p.position}f}" for x in position]
    parts.append("1" if contact else "0")
    if force is None or not np.all(np.isfinite(force)):
        parts += [""] * D
    else:
        parts += [f"{x:.{p.force}f}" for x in force]
    if contact and normal is not None and np.all(np.isfinite(normal)):
        parts += [f"{x:.{p.normal}f}" for x in normal]
    else:
        parts += [""] * D
    return with_checksum(",".join(parts))

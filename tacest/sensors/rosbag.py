"""Run files from ROS bags (``tacest record --source rosbag BAG --mapping MAP.toml``).

Reads ROS 1 bags (``.bag``), ROS 2 bags (a folder with ``metadata.yaml``, sqlite3 or
MCAP storage) and bare ``.mcap`` / ``.db3`` files with the pure-Python ``rosbags``
library, and resamples the streams named in a small TOML mapping onto the uniform clock
of a run file (SPEC).  docs/rosbag.md documents the mapping with an example.

Streams (per finger f):

=============  =========================================================  ==============
run field      message types (any other: ``field`` names a dotted path)   resampling
=============  =========================================================  ==============
position       geometry_msgs/PoseStamped, PointStamped, TransformStamped  at t[k]
               or a TF frame (``tf = "frame"``, /tf and /tf_static)
force          geometry_msgs/WrenchStamped (``wrench.force``),            mean over
               Vector3Stamped                                             (t[k-1], t[k]]
contact        std_msgs/Bool (``data``), or any numeric field and a       any over
               ``threshold``; or ``force_threshold`` N on the force       (t[k-1], t[k]]
normal         geometry_msgs/Vector3Stamped (``vector``), made unit; or   mean over
               ``from_force = true``: -force / |force|                    (t[k-1], t[k]]
=============  =========================================================  ==============

Frames.  Every vector is expressed in the mapping's ``world_frame``: a message whose
``header.frame_id`` is another frame is transformed at its own stamp through the TF tree
of ``/tf`` and ``/tf_static`` (translation interpolated linearly, rotation by normalised
linear interpolation of quaternions between the two bracketing transforms); forces and
normals are rotated only.  For ``dim = 2`` the world axes named by ``plane`` become
tacest's x and y (default ``"xz"``: ROS's z up is tacest's y up).

Clock.  Times are the messages' ``header.stamp`` (``stamp = "bag"``: the bag's receive
time; messages without a header always use it), integers in ns.  The run starts at the
latest first message of the position, force and contact streams and ends at the earliest
last one; sample k is at ``t0 + k·dt``.  A stream has a **gap** at sample k when the two
messages that bracket t[k] are more than ``max_gap`` apart (default 1.5 × the stream's
median message period, so one dropped message is a gap) or t[k] lies outside the
stream; interval streams are not in a gap where a message falls in (t[k-1], t[k]].
A sample where any stream of finger f is in a gap is missing for that finger
(``/quality/missing_finger``, and ``/quality/missing`` their OR): its contact is 0,
force 0, normal NaN and position interpolated (docs/formats.md).  A contact sample whose
normal has a gap is missing too (SPEC needs a unit normal wherever contact = 1).

Errors (missing bag or topic, an unknown message type, an empty topic, no TF chain,
a bad mapping) are TacestErrors of one line naming the bag or mapping file and topic.
"""

from __future__ import annotations

import json
import logging
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from tacest.errors import TacestError
from tacest.io.run import Run

log = logging.getLogger(__name__)

#: a stream is in a gap where its bracketing messages are further apart than this many
#: median periods (one dropped message doubles the spacing: 2 > 1.5; jitter of a few
#: tens of percent stays below it)
GAP_FACTOR = 1.5
#: m/s², gravity of the run file when the mapping does not say
STANDARD_GRAVITY = 9.81
#: |force| below this (N) gives no direction for ``normal = { from_force = true }``
MIN_FORCE_FOR_NORMAL = 1e-9
ROLES = ("position", "force", "contact", "normal")
_TOP_KEYS = {"dt", "dim", "plane", "world_frame", "stamp", "max_gap", "ground_height", "gravity", "fingers",
             "prior", "typestore"}
_STREAM_KEYS = {"topic", "tf", "field", "scale", "threshold", "force_threshold", "from_force", "max_gap"}
#: the value each message type gives for each role (dotted attribute paths)
_DEFAULT_FIELDS = {
    "geometry_msgs/msg/PoseStamped": "pose.position",
    "geometry_msgs/msg/PointStamped": "point",
    "geometry_msgs/msg/TransformStamped": "transform.translation",
    "geometry_msgs/msg/WrenchStamped": "wrench.force",
    "geometry_msgs/msg/Vector3Stamped": "vector",
    "std_msgs/msg/Bool": "data",
    "std_msgs/msg/Float64": "data",
    "std_msgs/msg/Float32": "data",
    "std_msgs/msg/UInt8": "data",
    "std_msgs/msg/Int32": "data",
}
_PLANES = {"xz": (0, 2), "xy": (0, 1), "yz": (1, 2)}


# ---------------------------------------------------------------------------------
# the mapping


@dataclass
class StreamSpec:
    """Where one run field of one finger comes from (module docstring)."""

    role: str
    topic: Optional[str] = None
    tf: Optional[str] = None
    field: Optional[str] = None
    scale: float = 1.0
    threshold: float = 0.5
    force_threshold: Optional[float] = None
    from_force: bool = False
    max_gap: Optional[float] = None  # s


@dataclass
class FingerSpec:
    radius: float
    position: StreamSpec
    force: Optional[StreamSpec] = None
    contact: Optional[StreamSpec] = None
    normal: Optional[StreamSpec] = None


@dataclass
class Mapping:
    """A TOML mapping of bag topics and frames to run file fields (docs/rosbag.md)."""

    dt: float
    fingers: list
    dim: int = 3
    plane: str = "xz"
    world_frame: str = "world"
    stamp: str = "header"
    max_gap: Optional[float] = None
    ground_height: float = 0.0
    gravity: Optional[list] = None
    prior: dict = field(default_factory=dict)
    typestore: str = "ROS2_HUMBLE"
    text: str = ""


def _bad(path, key, problem):
    raise TacestError(f"{path}: {key}: {problem}")


def _number(path, key, v, positive=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        _bad(path, key, f"expected a number, got {v!r}")
    if positive and v <= 0:
        _bad(path, key, f"must be > 0, got {v!r}")
    return float(v)


def _stream(path, where, role, raw) -> StreamSpec:
    if isinstance(raw, str):
        raw = {"topic": raw}
    if not isinstance(raw, dict):
        _bad(path, where, "expected a table such as { topic = \"/name\" }")
    unknown = set(raw) - _STREAM_KEYS
    if unknown:
        _bad(path, f"{where}.{sorted(unknown)[0]}", f"unknown key (known: {', '.join(sorted(_STREAM_KEYS))})")
    s = StreamSpec(role=role, topic=raw.get("topic"), tf=raw.get("tf"), field=raw.get("field"))
    for k in ("scale", "threshold"):
        if k in raw:
            setattr(s, k, _number(path, f"{where}.{k}", raw[k]))
    if "max_gap" in raw:
        s.max_gap = _number(path, f"{where}.max_gap", raw["max_gap"], positive=True)
    if "force_threshold" in raw:
        if role != "contact":
            _bad(path, f"{where}.force_threshold", "only for contact")
        s.force_threshold = _number(path, f"{where}.force_threshold", raw["force_threshold"], positive=True)
    if raw.get("from_force"):
        if role != "normal":
            _bad(path, f"{where}.from_force", "only for normal")
        s.from_force = True
    sources = [x for x in (s.topic, s.tf, s.force_threshold, s.from_force or None) if x is not None]
    if len(sources) != 1:
        _bad(path, where, "give exactly one of topic" + (", tf" if role == "position" else "")
             + (", force_threshold" if role == "contact" else "") + (", from_force" if role == "normal" else ""))
    if s.tf is not None and role != "position":
        _bad(path, f"{where}.tf", "a TF frame can give the position only")
    return s


def read_mapping(path) -> Mapping:
    """Read and check a TOML mapping (docs/rosbag.md); a TacestError naming the file
    and key for anything wrong."""
    path = Path(path)
    if not path.is_file():
        raise TacestError(f"{path}: mapping file not found")
    text = path.read_text()
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise TacestError(f"{path}: not valid TOML ({exc})") from None
    unknown = set(raw) - _TOP_KEYS
    if unknown:
        _bad(path, sorted(unknown)[0], f"unknown key (known: {', '.join(sorted(_TOP_KEYS))})")
    if "dt" not in raw:
        _bad(path, "dt", "required: the run file's sample period in s")
    m = Mapping(dt=_number(path, "dt", raw["dt"], positive=True), fingers=[], text=text)
    m.dim = int(raw.get("dim", 3))
    if m.dim not in (2, 3):
        _bad(path, "dim", f"must be 2 or 3, got {raw.get('dim')!r}")
    m.plane = str(raw.get("plane", "xz"))
    if m.plane not in _PLANES:
        _bad(path, "plane", f"one of {', '.join(_PLANES)}, got {m.plane!r}")
    m.world_frame = str(raw.get("world_frame", "world"))
    m.stamp = str(raw.get("stamp", "header"))
    if m.stamp not in ("header", "bag"):
        _bad(path, "stamp", f"'header' or 'bag', got {m.stamp!r}")
    if "max_gap" in raw:
        m.max_gap = _number(path, "max_gap", raw["max_gap"], positive=True)
    m.ground_height = _number(path, "ground_height", raw.get("ground_height", 0.0))
    if "gravity" in raw:
        g = raw["gravity"]
        if not isinstance(g, list) or len(g) != m.dim:
            _bad(path, "gravity", f"expected a list of {m.dim} numbers")
        m.gravity = [_number(path, "gravity", v) for v in g]
    m.prior = dict(raw.get("prior", {}))
    m.typestore = str(raw.get("typestore", "ROS2_HUMBLE"))
    fingers = raw.get("fingers")
    if not isinstance(fingers, list) or not fingers:
        _bad(path, "fingers", "required: one [[fingers]] table per fingertip")
    for f, fr in enumerate(fingers):
        where = f"fingers[{f}]"
        unknown = set(fr) - {"radius", *ROLES}
        if unknown:
            _bad(path, f"{where}.{sorted(unknown)[0]}", f"unknown key (known: radius, {', '.join(ROLES)})")
        if "radius" not in fr:
            _bad(path, f"{where}.radius", "required: the fingertip radius in m")
        if "position" not in fr:
            _bad(path, f"{where}.position", "required")
        spec = FingerSpec(radius=_number(path, f"{where}.radius", fr["radius"], positive=True),
                          position=_stream(path, f"{where}.position", "position", fr["position"]))
        for role in ("force", "contact", "normal"):
            if role in fr:
                setattr(spec, role, _stream(path, f"{where}.{role}", role, fr[role]))
        if spec.contact is None:
            _bad(path, f"{where}.contact", "required: a topic, or force_threshold = N with a force stream")
        if spec.normal is None:
            _bad(path, f"{where}.normal", "required: a topic, or from_force = true with a force stream")
        if (spec.contact.force_threshold is not None or spec.normal.from_force) and spec.force is None:
            _bad(path, f"{where}.force", "required when contact or normal come from the force")
        m.fingers.append(spec)
    return m


# ---------------------------------------------------------------------------------
# reading the bag


@dataclass
class _Messages:
    """One topic's messages: stamps (N,) int ns, values (N, d), frame ids (N,) str."""

    topic: str
    msgtype: str
    stamps: np.ndarray
    values: np.ndarray
    frames: list


def _get(msg, dotted: str):
    obj = msg
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def _as_vector(v) -> np.ndarray:
    if hasattr(v, "x"):
        return np.array([float(v.x), float(v.y), float(v.z)])
    return np.array([float(v)])


def _stamp_ns(msg, bag_ns: int, use_header: bool) -> int:
    h = getattr(msg, "header", None)
    if use_header and h is not None:
        return int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec)
    return int(bag_ns)


class _Bag:
    """Every message of the topics a mapping needs, read in one pass."""

    def __init__(self, bag, mapping: Mapping):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(bag)
        if not self.path.exists():
            raise TacestError(f"{self.path}: no such bag (a .bag file, a ROS 2 bag folder, or a .mcap/.db3 file)")
        try:
            store = get_typestore(getattr(Stores, mapping.typestore))
        except AttributeError:
            raise TacestError(f"typestore {mapping.typestore!r}: unknown (e.g. ROS1_NOETIC, ROS2_HUMBLE)") from None
        topics = {s.topic for f in mapping.fingers for s in (f.position, f.force, f.contact, f.normal)
                  if s is not None and s.topic}
        fields = {s.topic: s.field for f in mapping.fingers for s in (f.position, f.force, f.contact, f.normal)
                  if s is not None and s.topic}
        self.tf_edges = {}  # (parent, child) -> (stamps list, trans list, quat list, static)
        raw = {t: ([], [], [], None) for t in topics}
        use_header = mapping.stamp == "header"
        try:
            reader = AnyReader([self.path], default_typestore=store)
            reader.open()
        except Exception as exc:  # rosbags' own errors, or an unreadable file
            raise TacestError(f"{self.path}: not a readable ROS bag ({exc.__class__.__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
        try:
            available = {c.topic: c.msgtype for c in reader.connections}
            for t in sorted(topics):
                if t not in available:
                    raise TacestError(f"{self.path}: topic {t} is not in the bag (topics: "
                                      f"{', '.join(sorted(available)) or 'none'})")
            tf_topics = [t for t in ("/tf", "/tf_static") if t in available]
            conns = [c for c in reader.connections if c.topic in topics or c.topic in tf_topics]
            for t in topics:
                typ = available[t]
                if fields[t] is None and typ not in _DEFAULT_FIELDS:
                    raise TacestError(f"{self.path}: {t}: message type {typ} is not one tacest knows (known: "
                                      f"{', '.join(sorted(_DEFAULT_FIELDS))}); name the value with field = \"...\"")
            for conn, bag_ns, data in reader.messages(connections=conns):
                try:
                    msg = reader.deserialize(data, conn.msgtype)
                except Exception as exc:
                    raise TacestError(f"{self.path}: {conn.topic}: cannot decode {conn.msgtype} ({exc})") from None
                if conn.topic in tf_topics:  # TF positions, and frames of other messages
                    self._add_tf(msg, conn.topic == "/tf_static", use_header, bag_ns)
                    if conn.topic not in topics:
                        continue
                path = fields[conn.topic] or _DEFAULT_FIELDS[conn.msgtype]
                try:
                    value = _as_vector(_get(msg, path))
                except (AttributeError, TypeError, ValueError):
                    raise TacestError(f"{self.path}: {conn.topic}: {conn.msgtype} has no numeric field {path!r}") \
                        from None
                st, vals, frames, _ = raw[conn.topic]
                st.append(_stamp_ns(msg, bag_ns, use_header))
                vals.append(value)
                h = getattr(msg, "header", None)
                frames.append("" if h is None else str(h.frame_id))
        finally:
            reader.close()
        self.messages = {}
        for t, (st, vals, frames, _) in raw.items():
            if not st:
                raise TacestError(f"{self.path}: {t}: no messages")
            order = np.argsort(np.asarray(st, np.int64), kind="stable")
            self.messages[t] = _Messages(t, available[t], np.asarray(st, np.int64)[order],
                                         np.asarray(vals, float)[order], [frames[i] for i in order])
        for key, (st, tr, q, static) in self.tf_edges.items():
            order = np.argsort(np.asarray(st, np.int64), kind="stable")
            self.tf_edges[key] = (np.asarray(st, np.int64)[order], np.asarray(tr, float)[order],
                                  np.asarray(q, float)[order], static)
        self.parent = {child: parent for (parent, child) in self.tf_edges}

    def _add_tf(self, msg, static, use_header, bag_ns):
        for tr in msg.transforms:
            parent, child = str(tr.header.frame_id).lstrip("/"), str(tr.child_frame_id).lstrip("/")
            key = (parent, child)
            st, trans, quat, _ = self.tf_edges.get(key, ([], [], [], static))
            t, r = tr.transform.translation, tr.transform.rotation
            st.append(_stamp_ns(tr, bag_ns, use_header))
            trans.append([t.x, t.y, t.z])
            quat.append([r.w, r.x, r.y, r.z])
            self.tf_edges[key] = (st, trans, quat, static)

    # -- TF ----------------------------------------------------------------------------
    def _chain(self, frame: str) -> list:
        """Frames from ``frame`` up to its root."""
        out, seen = [frame], {frame}
        while out[-1] in self.parent:
            p = self.parent[out[-1]]
            if p in seen:
                raise TacestError(f"{self.path}: /tf: the frames form a loop at {p!r}")
            out.append(p)
            seen.add(p)
        return out

    def _edge_at(self, parent, child, t_ns, gap_ns):
        """(R (N,3,3), p (N,3), ok (N,)) of the edge parent->child at times t_ns."""
        from tacest.geometry.transforms import quat_to_matrix

        st, trans, quat, static = self.tf_edges[(parent, child)]
        t_ns = np.asarray(t_ns, np.int64)
        if static or len(st) == 1:
            R = np.broadcast_to(quat_to_matrix(quat[-1]), (len(t_ns), 3, 3))
            return R, np.broadcast_to(trans[-1], (len(t_ns), 3)), np.ones(len(t_ns), bool)
        i0, i1, w, ok = _bracket(st, t_ns, gap_ns if gap_ns else _default_gap(st))
        q0, q1 = quat[i0], quat[i1]
        q1 = np.where(np.sum(q0 * q1, axis=1, keepdims=True) < 0, -q1, q1)
        q = (1 - w)[:, None] * q0 + w[:, None] * q1
        p = (1 - w)[:, None] * trans[i0] + w[:, None] * trans[i1]
        return quat_to_matrix(q), p, ok

    def transform(self, target: str, source: str, t_ns, gap_ns=None):
        """(R, p, ok): the pose of frame ``source`` in frame ``target`` at times t_ns (N,)
        (R (N, 3, 3), p (N, 3) m, ok (N,) bool where every moving edge is bracketed)."""
        target, source = target.lstrip("/"), source.lstrip("/")
        N = len(t_ns)
        up_s, up_t = self._chain(source), self._chain(target)
        common = next((f for f in up_s if f in up_t), None)
        if common is None:
            raise TacestError(f"{self.path}: /tf: no transform chain from {target!r} to {source!r} (frames: "
                              f"{', '.join(sorted(set(self.parent) | set(self.parent.values()))) or 'none'})")

        def to_common(chain):
            R, p, ok = np.broadcast_to(np.eye(3), (N, 3, 3)).copy(), np.zeros((N, 3)), np.ones(N, bool)
            for child, parent in zip(chain, chain[1:]):
                if child == common:
                    break
                Re, pe, oke = self._edge_at(parent, child, t_ns, gap_ns)
                # x_parent = Re x_child + pe;  x_common = R_acc x_parent + p_acc is built outward-in
                p = np.einsum("nij,nj->ni", Re, p) + pe
                R = np.einsum("nij,njk->nik", Re, R)
                ok &= oke
            return R, p, ok

        Rs, ps, oks = to_common(up_s)
        Rt, pt, okt = to_common(up_t)
        RtT = np.transpose(Rt, (0, 2, 1))
        return (np.einsum("nij,njk->nik", RtT, Rs), np.einsum("nij,nj->ni", RtT, ps - pt), oks & okt)


# ---------------------------------------------------------------------------------
# resampling


def _default_gap(stamps) -> int:
    """GAP_FACTOR x the median spacing (ns) of the stamps (N,); 0 for fewer than two."""
    d = np.diff(np.asarray(stamps, np.int64))
    d = d[d > 0]
    return int(GAP_FACTOR * np.median(d)) if d.size else 0


def _bracket(stamps, t_ns, gap_ns):
    """For times t_ns (T,): indices i0, i1 of the messages bracketing each time, the
    linear weight w of i1, and ok where the bracket is within gap_ns (or a message is at
    the time exactly).  stamps (N,) sorted int ns."""
    s = np.asarray(stamps, np.int64)
    t = np.asarray(t_ns, np.int64)
    i1 = np.searchsorted(s, t, side="left")  # s[i1] >= t
    exact = (i1 < len(s)) & (s[np.minimum(i1, len(s) - 1)] == t)
    i0 = np.clip(i1 - 1, 0, len(s) - 1)
    i1c = np.clip(i1, 0, len(s) - 1)
    i0 = np.where(exact, i1c, i0)
    span = (s[i1c] - s[i0]).astype(float)
    w = np.where(span > 0, (t - s[i0]) / np.where(span > 0, span, 1.0), 0.0)
    w = np.clip(w, 0.0, 1.0)
    inside = (i1 > 0) & (i1 < len(s))
    ok = exact | (inside & (s[i1c] - s[i0] <= gap_ns))
    return i0, i1c, w, ok


def _interval_index(stamps, t0_ns, dt_ns):
    """Sample index k of each message: the interval (t[k-1], t[k]] holding its stamp."""
    return -((t0_ns - np.asarray(stamps, np.int64)) // dt_ns)  # ceil((s - t0) / dt)


def _resample_at(msgs: _Messages, t_ns, gap_ns):
    i0, i1, w, ok = _bracket(msgs.stamps, t_ns, gap_ns)
    v = (1 - w)[:, None] * msgs.values[i0] + w[:, None] * msgs.values[i1]
    return v, ok


def _resample_interval(msgs: _Messages, t_ns, t0_ns, dt_ns, gap_ns, how: str):
    """Per-interval mean ('mean') or max ('max') of the messages in (t[k-1], t[k]];
    elsewhere the bracketing interpolation ('mean') or the last value held ('max')."""
    T = len(t_ns)
    k = _interval_index(msgs.stamps, t0_ns, dt_ns)
    sel = (k >= 0) & (k < T)
    d = msgs.values.shape[1]
    count = np.bincount(k[sel], minlength=T)
    have = count > 0
    out = np.zeros((T, d))
    if how == "mean":
        for j in range(d):
            out[:, j] = np.bincount(k[sel], weights=msgs.values[sel, j], minlength=T)
        out[have] /= count[have, None]
        v, ok = _resample_at(msgs, t_ns, gap_ns)
    else:
        out[:] = -np.inf
        np.maximum.at(out, k[sel], msgs.values[sel])
        i0, i1, w, ok = _bracket(msgs.stamps, t_ns, gap_ns)
        v = msgs.values[np.where(w >= 1.0, i1, i0)]
    out[~have] = v[~have]
    return out, have | ok


@dataclass
class RosbagSummary:
    samples: int
    missing: int
    missing_per_finger: list
    messages: dict
    t0_ns: int

    def line(self) -> str:
        per = ", ".join(f"finger {f}: {n}" for f, n in enumerate(self.missing_per_finger))
        return f"{self.samples} samples, {self.missing} missing ({per})"


def _to_world(bag: _Bag, msgs: _Messages, world: str, rotate_only: bool, gap_ns) -> tuple:
    """The messages' vectors in the world frame (values (N, 3)) and ok (N,) where the
    transform is known; frames '' and world pass through."""
    vals = msgs.values.copy()
    ok = np.ones(len(vals), bool)
    frames = np.array([f.lstrip("/") for f in msgs.frames], dtype=object)
    for fr in sorted(set(frames) - {"", world.lstrip("/")}):
        idx = np.flatnonzero(frames == fr)
        R, p, okf = bag.transform(world, fr, msgs.stamps[idx], gap_ns)
        v = np.einsum("nij,nj->ni", R, vals[idx])
        vals[idx] = v if rotate_only else v + p
        ok[idx] = okf
    return vals, ok


def _gap_ns(spec: StreamSpec, m: Mapping, stamps) -> int:
    """The largest message spacing (ns) of a stream that is not a gap: the stream's
    ``max_gap``, else the mapping's, else GAP_FACTOR x the median spacing of ``stamps``."""
    g = spec.max_gap if spec.max_gap is not None else m.max_gap
    return int(round(g * 1e9)) if g is not None else _default_gap(stamps)


def _world_streams(b: _Bag, m: Mapping) -> dict:
    """{(finger, role): (_Messages, StreamSpec)} of the topic-backed streams, their
    vectors in the world frame (positions transformed, forces and normals rotated) and
    scaled; messages whose stamp TF does not cover are dropped."""
    streams = {}
    for f, fs in enumerate(m.fingers):
        for role in ROLES:
            spec = getattr(fs, role)
            if spec is None or spec.topic is None:
                continue
            msgs = b.messages[spec.topic]
            vals = msgs.values
            if role != "contact":
                if vals.shape[1] != 3:
                    raise TacestError(f"{b.path}: {spec.topic}: {role} needs a 3-vector, the field gives "
                                      f"{vals.shape[1]} number(s)")
                vals, okw = _to_world(b, msgs, m.world_frame, rotate_only=(role != "position"), gap_ns=None)
                keep = okw
            else:
                keep = np.ones(len(vals), bool)
            vals = vals * spec.scale
            if not np.any(keep):
                raise TacestError(f"{b.path}: {spec.topic}: no message could be put in frame {m.world_frame!r} "
                                  "(TF does not cover its stamps)")
            streams[(f, role)] = (_Messages(spec.topic, msgs.msgtype, msgs.stamps[keep], vals[keep],
                                            [msgs.frames[i] for i in np.flatnonzero(keep)]), spec)
    return streams


def _run_clock(b: _Bag, m: Mapping, streams: dict, dt_ns: int) -> tuple:
    """(t0, t_ns): the run's first time (ns) and its uniform sample times (T,) ns, from
    the latest first to the earliest last message of the streams that define samples
    (positions, forces, contacts; the moving TF edges of TF positions)."""
    firsts, lasts = [], []
    for (f, role), (msgs, spec) in streams.items():
        if role != "normal":
            firsts.append(int(msgs.stamps[0]))
            lasts.append(int(msgs.stamps[-1]))
    for fs in m.fingers:
        if fs.position.tf:
            for child, parent in zip(b._chain(fs.position.tf), b._chain(fs.position.tf)[1:]):
                st, _, _, static = b.tf_edges[(parent, child)]
                if not static and len(st) > 1:
                    firsts.append(int(st[0]))
                    lasts.append(int(st[-1]))
    if not firsts:
        raise TacestError(f"{b.path}: no time-stamped stream to make a clock from (TF positions are all static)")
    t0, t1 = max(firsts), min(lasts)
    if t1 - t0 < dt_ns:
        raise TacestError(f"{b.path}: the streams overlap for {(t1 - t0) / 1e9:.3g} s, less than one sample "
                          f"(dt = {m.dt} s)")
    T = int((t1 - t0) // dt_ns) + 1
    return t0, t0 + dt_ns * np.arange(T, dtype=np.int64)


def _finger_samples(b: _Bag, m: Mapping, streams: dict, f: int, t_ns, dt_ns: int) -> dict:
    """Finger ``f``'s streams on the run's clock, in the world frame (3-vectors):
    ``position`` (T, 3), ``force`` (T, 3) or None, ``contact`` (T,) bool, ``normal``
    (T, 3), ``normal_ok`` (T,) where the normal stream is not in a gap, ``missing`` (T,)
    where any other stream is."""
    fs = m.fingers[f]
    t0 = int(t_ns[0])
    T = len(t_ns)
    missing = np.zeros(T, bool)
    if fs.position.tf:
        _, p, ok = b.transform(m.world_frame, fs.position.tf, t_ns, _gap_ns(fs.position, m, []) or None)
        p_w = p * fs.position.scale
    else:
        msgs, spec = streams[(f, "position")]
        p_w, ok = _resample_at(msgs, t_ns, _gap_ns(spec, m, msgs.stamps))
    missing |= ~ok
    f_w = None
    if fs.force is not None:
        msgs, spec = streams[(f, "force")]
        f_w, ok = _resample_interval(msgs, t_ns, t0, dt_ns, _gap_ns(spec, m, msgs.stamps), "mean")
        missing |= ~ok
    if fs.contact.force_threshold is not None:
        c = np.linalg.norm(f_w, axis=1) > fs.contact.force_threshold
    else:
        msgs, spec = streams[(f, "contact")]
        cv, ok = _resample_interval(msgs, t_ns, t0, dt_ns, _gap_ns(spec, m, msgs.stamps), "max")
        c = cv[:, 0] > spec.threshold
        missing |= ~ok
    if fs.normal.from_force:
        mag = np.linalg.norm(f_w, axis=1, keepdims=True)
        n_w = np.where(mag > MIN_FORCE_FOR_NORMAL, -f_w / np.maximum(mag, MIN_FORCE_FOR_NORMAL), np.nan)
        n_ok = np.ones(T, bool)
    else:
        msgs, spec = streams[(f, "normal")]
        n_w, n_ok = _resample_interval(msgs, t_ns, t0, dt_ns, _gap_ns(spec, m, msgs.stamps), "mean")
    return {"position": p_w, "force": f_w, "contact": c, "normal": n_w, "normal_ok": n_ok, "missing": missing}


def _run_arrays(b: _Bag, m: Mapping, streams: dict, t_ns, dt_ns: int) -> dict:
    """The run's finger arrays on its clock: ``finger_position`` (T, F, D), ``force``
    (T, F, D) or None, ``contact`` (T, F), ``normal`` (T, F, D) unit or NaN, and
    ``missing`` (T, F) bool, with the placeholders of docs/formats.md where a finger's
    sample is missing (contact 0, force 0, normal NaN, position interpolated)."""
    T, F, D = len(t_ns), len(m.fingers), m.dim
    axes = _PLANES[m.plane] if D == 2 else (0, 1, 2)
    pos = np.zeros((T, F, D))
    force = np.zeros((T, F, D)) if any(fs.force is not None for fs in m.fingers) else None
    contact = np.zeros((T, F), np.uint8)
    normal = np.full((T, F, D), np.nan)
    missing = np.zeros((T, F), bool)
    for f in range(F):
        fx = _finger_samples(b, m, streams, f, t_ns, dt_ns)
        pos[:, f] = fx["position"][:, axes]
        c = fx["contact"]
        n = fx["normal"][:, axes]
        nn = np.linalg.norm(n, axis=1)
        good_n = fx["normal_ok"] & np.isfinite(nn) & (nn > 0)
        missing[:, f] = fx["missing"] | (c & ~good_n)
        if fx["force"] is not None:
            force[:, f] = fx["force"][:, axes]
        contact[:, f] = c
        normal[:, f] = np.where(good_n[:, None], n / np.where(nn > 0, nn, 1.0)[:, None], np.nan)
    # placeholders where missing (docs/formats.md): position interpolated over the gap
    for f in range(F):
        bad = missing[:, f]
        if np.any(bad) and not np.all(bad):
            good = np.flatnonzero(~bad)
            for j in range(D):
                pos[bad, f, j] = np.interp(np.flatnonzero(bad), good, pos[good, f, j])
    contact[missing] = 0
    normal[contact == 0] = np.nan
    if force is not None:
        force[missing] = 0.0
    return {"finger_position": pos, "force": force, "contact": contact, "normal": normal, "missing": missing}


def record_rosbag(bag, mapping_path) -> Run:
    """A Run (SPEC, source ``rosbag``) from the bag ``bag`` and the TOML mapping
    ``mapping_path`` (module docstring): the streams in the world frame
    (:func:`_world_streams`), the clock (:func:`_run_clock`), the finger arrays on it
    (:func:`_run_arrays`)."""
    m = read_mapping(mapping_path)
    b = _Bag(bag, m)
    dt_ns = int(round(m.dt * 1e9))
    streams = _world_streams(b, m)
    t0, t_ns = _run_clock(b, m, streams, dt_ns)
    arrays = _run_arrays(b, m, streams, t_ns, dt_ns)
    missing = arrays.pop("missing")
    T, D = len(t_ns), m.dim
    gravity = m.gravity if m.gravity is not None else ([0.0, -STANDARD_GRAVITY] if D == 2
                                                       else [0.0, 0.0, -STANDARD_GRAVITY])
    summary = RosbagSummary(samples=T, missing=int(np.any(missing, axis=1).sum()),
                            missing_per_finger=[int(x) for x in missing.sum(axis=0)],
                            messages={t: int(len(ms.stamps)) for t, ms in b.messages.items()}, t0_ns=int(t0))
    run = Run(dim=D, dt=dt_ns / 1e9, time=(t_ns - t0) / 1e9, gravity=np.asarray(gravity, float), source="rosbag",
              finger_radius=np.array([fs.radius for fs in m.fingers]), ground_height=m.ground_height,
              prior=m.prior, missing=np.any(missing, axis=1).astype(np.uint8),
              missing_finger=missing.astype(np.uint8), **arrays,
              extra_attrs={"rosbag_file": str(b.path), "rosbag_mapping": m.text, "rosbag_t0_ns": int(t0),
                           "rosbag_summary": json.dumps({"samples": T, "missing": summary.missing,
                                                         "missing_per_finger": summary.missing_per_finger,
                                                         "messages": summary.messages})})
    log.info("%s: %s", b.path, summary.line())
    return run

"""Pokes: the action parameterization and the fingertip paths that carry them out.

A poke is the vector ``[finger, approach_angle, target_x, target_y, depth, speed]``
(:data:`POKE_NAMES`; written to /actions/params with attrs kind = ``"poke"``):

- ``finger``: index of the fingertip that pokes (0-based);
- ``approach_angle``: rad, world frame, the direction FROM which the finger comes,
  ``d = (cos a, sin a)``; in [0, π] so it comes from above the ground (random pokes
  use [10°, 65°] or [115°, 170°]: a push from steeper above only presses the object
  onto the ground, one along the ground would drag the finger on it);
- ``target_x, target_y``: m, world frame, the point it aims at (random pokes: the true
  centroid at poke start; planned pokes: the estimate's);
- ``depth``: m, how far the finger goes on past the point where it first touches the
  object (as a guarded move would: approach until touch, then push ``depth`` more);
- ``speed``: m/s along the approach line.

The fingertip path of one poke (a piecewise-linear motion of the control body):

1. transit: up to a safe height above the object, across, down to the start point
   ``target + d·(s_touch + CLEARANCE)``, at TRANSIT_SPEED; idle fingers lift to the
   safe height if they are below it;
2. approach: straight to ``target + d·(s_touch - depth)`` at ``speed`` (random pokes:
   the speed that makes this 1 s), where ``s_touch`` is the distance from the target
   along d at which the finger circle first touches the object in its pose at poke
   start (0 if the line misses it);
3. retreat: straight back to the start point in RETREAT_TIME.

(tacest.sim.record then holds the fingers still until the object is at rest.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tacest.errors import TacestError
from tacest.io.plan import POKE_NAMES  # noqa: F401  (re-exported: the one definition)

POKE_KIND = "poke"

#: m, start of the approach this far outside the first touch
CLEARANCE = 0.02
#: s, the random pokes' approach duration (the issue: "a 1 s straight motion")
APPROACH_TIME = 1.0
#: s, duration of the retreat back to the start point
RETREAT_TIME = 0.3
#: m/s, speed of the transit between pokes
TRANSIT_SPEED = 0.5
#: m, transit height above the object's top (finger surface to object)
SAFE_MARGIN = 0.02
#: random approach angles from the right, rad (mirrored for pokes from the left): away
#: from grazing lines along the ground and from steep pushes that only press down
RANDOM_ANGLE_RANGE = (math.radians(10.0), math.radians(65.0))
#: random depth past the first touch, m
RANDOM_DEPTH_RANGE = (0.01, 0.03)
#: accepted speeds, m/s (slower than 1 mm/s would take minutes; faster than 1 m/s is a hit)
SPEED_LIMITS = (1e-3, 1.0)
#: accepted depths, m: up to the largest object (SIZE_BOUND of the recorder, 0.3 m) and
#: more: a fast poke overshoots the first touch by 1.5 object sizes, like a robot that
#: aims at a point behind the object
DEPTH_LIMITS = (0.0, 0.5)


@dataclass(frozen=True)
class PokeStyle:
    """How a style draws its random pokes (2-D and 3-D alike; docs/simulation.md).

    elevation : (lo, hi) deg, approach direction above the horizontal (2-D: mirrored
    from the left with probability 1/2; 3-D: any azimuth); speed : (lo, hi) m/s along
    the approach; depth : (lo, hi) past the first touch, in object sizes (the largest
    extent); height : (lo, hi) target height above the ground as a fraction of the
    object's top (0.5: a box's centre; near 1: a high poke that tips it over); offset :
    (lo, hi) of the 3-D target's sideways offset from the centroid across the approach,
    in object sizes, either side (spin about the vertical)."""

    name: str
    elevation: tuple
    speed: tuple
    depth: tuple
    height: tuple
    offset: tuple = (0.0, 0.0)
    doc: str = ""


#: the styles of random pokes beside ``gentle`` (the default: random_poke's own draws,
#: slow pokes at the centroid that slide the object and hardly tip it).  The dynamic
#: ones: ``fast`` pokes at any height, ``high`` pokes near the top that tip and topple,
#: ``flick`` pokes low and fast after which the object slides and spins free
POKE_STYLES = {
    "fast": PokeStyle("fast", elevation=(5.0, 40.0), speed=(0.1, 0.6), depth=(0.3, 1.5), height=(0.3, 0.75),
                      offset=(0.0, 0.2), doc="0.1-0.6 m/s at any height, overshooting up to 1.5 object sizes"),
    "high": PokeStyle("high", elevation=(0.0, 25.0), speed=(0.1, 0.4), depth=(0.6, 1.5), height=(0.75, 0.95),
                      offset=(0.0, 0.1), doc="near the top, overshooting: the object tips over and topples"),
    "flick": PokeStyle("flick", elevation=(0.0, 20.0), speed=(0.4, 0.6), depth=(0.15, 0.5), height=(0.1, 0.35),
                       offset=(0.15, 0.4), doc="low and fast, off centre: the object slides and spins free"),
}
#: what ``--poke-style`` accepts: one style, or a mix whose pokes draw their style in turn
POKE_MIXES = {"gentle": ("gentle",), "fast": ("fast",), "high": ("high",), "flick": ("flick",),
              "dynamic": ("fast", "high", "flick"), "mixed": ("gentle", "fast", "high", "flick")}


def check_poke_style(name: str) -> str:
    """The name of a poke style or mix (POKE_MIXES); a TacestError otherwise."""
    if name not in POKE_MIXES:
        raise TacestError(f"unknown poke style {name!r}; one of {', '.join(POKE_MIXES)}")
    return name


def check_fingers_per_action(k: int, n_fingers: int, dim: int) -> int:
    """k, the fingers that move together in one action, if 1 <= k <= n_fingers and (for
    k > 1) dim is 3 (tacest.sim3d.pokes); a TacestError otherwise."""
    if not 1 <= int(k) <= int(n_fingers):
        raise TacestError(f"--fingers-per-action must be in 1..{n_fingers} (the fingers), got {k}")
    if int(k) > 1 and int(dim) != 3:
        raise TacestError("several fingers per action are offered in 3-D only (--dim 3)")
    return int(k)


def style_of_poke(mix: str, rng: np.random.Generator, index: int) -> str:
    """The style of poke ``index`` of a recording in ``mix``: a single style always; a
    mix draws one per poke (uniformly; no draw for a single style, so the gentle
    recordings keep their random streams)."""
    styles = POKE_MIXES[check_poke_style(mix)]
    return styles[0] if len(styles) == 1 else styles[int(rng.integers(len(styles)))]


def draw_style(style: PokeStyle, rng: np.random.Generator, size: float) -> dict:
    """One draw of a style's parameters: elevation (rad), speed (m/s), depth (m, within
    DEPTH_LIMITS), height (fraction), offset (in sizes, with a random sign)."""
    elevation = math.radians(float(rng.uniform(*style.elevation)))
    speed = float(rng.uniform(*style.speed))
    depth = float(np.clip(rng.uniform(*style.depth) * size, *DEPTH_LIMITS))
    height = float(rng.uniform(*style.height))
    offset = float(rng.choice([-1.0, 1.0]) * rng.uniform(*style.offset))
    return {"elevation": elevation, "speed": speed, "depth": depth, "height": height, "offset": offset}


@dataclass
class Poke:
    """One poke; see the module docstring.  target__world : (2,) m."""

    finger: int
    approach_angle: float
    target__world: np.ndarray
    depth: float
    speed: float

    @property
    def direction__world(self) -> np.ndarray:
        """(2,) unit vector from the target towards where the finger comes from."""
        return np.array([math.cos(self.approach_angle), math.sin(self.approach_angle)])

    def to_vector(self) -> np.ndarray:
        """(6,) in the order of POKE_NAMES."""
        return np.array([self.finger, self.approach_angle, self.target__world[0], self.target__world[1],
                         self.depth, self.speed], float)

    @classmethod
    def from_vector(cls, vec, n_fingers: int, names=POKE_NAMES) -> "Poke":
        """A poke from a parameter vector whose entries are named ``names``.

        Checks every value (TacestError naming the bad one): finger index in range,
        angle in [0, π], finite target, depth in DEPTH_LIMITS, speed in SPEED_LIMITS.
        """
        names = [str(n) for n in names]
        vec = np.asarray(vec, float).reshape(-1)
        if len(names) != len(vec):
            raise TacestError(f"poke: {len(vec)} values for {len(names)} names")
        missing = [n for n in POKE_NAMES if n not in names]
        if missing:
            raise TacestError(f"poke: parameter(s) {', '.join(missing)} missing; a poke needs "
                              f"{', '.join(POKE_NAMES)}")
        p = {n: float(vec[names.index(n)]) for n in POKE_NAMES}
        for n, v in p.items():
            if not math.isfinite(v):
                raise TacestError(f"poke: {n} = {v} is not finite")
        f = p["finger"]
        if f != round(f) or not 0 <= f < n_fingers:
            raise TacestError(f"poke: finger = {f:g} is not a finger index in 0..{n_fingers - 1}")
        if not -1e-9 <= p["approach_angle"] <= math.pi + 1e-9:
            raise TacestError(f"poke: approach_angle = {p['approach_angle']:.4g} rad is outside [0, π] "
                              "(the finger must come from above the ground)")
        lo, hi = DEPTH_LIMITS
        if not lo <= p["depth"] <= hi:
            raise TacestError(f"poke: depth = {p['depth']:.4g} m is outside [{lo}, {hi}] m")
        lo, hi = SPEED_LIMITS
        if not lo <= p["speed"] <= hi:
            raise TacestError(f"poke: speed = {p['speed']:.4g} m/s is outside [{lo}, {hi}] m/s")
        return cls(finger=int(round(f)), approach_angle=p["approach_angle"],
                   target__world=np.array([p["target_x"], p["target_y"]]), depth=p["depth"], speed=p["speed"])


def random_poke(rng: np.random.Generator, centroid__world, n_fingers: int, style: str = "gentle",
                vertices__world=None, ground_height: float = 0.0) -> Poke:
    """A random poke of ``style`` (POKE_STYLES or ``gentle``).

    gentle: at the object's centroid (2,) m, random finger, angle U(10°, 65°) from the
    right or its mirror from the left, depth U(1, 3) cm, and the speed that makes the
    approach last APPROACH_TIME.  The other styles draw their elevation, speed, depth
    (in sizes of the object whose vertices__world (K, 2) m are given) and target height
    above ``ground_height`` (m) from their PokeStyle, from the right or the left."""
    if style != "gentle":
        V = np.asarray(vertices__world, float)
        size = float(np.max(np.ptp(V, axis=0)))
        finger = int(rng.integers(n_fingers))
        d = draw_style(POKE_STYLES[style], rng, size)
        angle = d["elevation"] if rng.random() < 0.5 else math.pi - d["elevation"]
        top = float(np.max(V[:, 1]))
        target = np.array([float(centroid__world[0]), ground_height + d["height"] * (top - ground_height)])
        return Poke(finger, angle, target, d["depth"], d["speed"])
    finger = int(rng.integers(n_fingers))
    angle = float(rng.uniform(*RANDOM_ANGLE_RANGE))
    if rng.random() < 0.5:
        angle = math.pi - angle
    depth = float(rng.uniform(*RANDOM_DEPTH_RANGE))
    return Poke(finger, angle, np.asarray(centroid__world, float).copy(), depth,
                (CLEARANCE + depth) / APPROACH_TIME)


@dataclass
class Path:
    """Piecewise-linear control path of every finger.

    times : (N,) s from the poke's start, non-decreasing, times[0] = 0;
    p_ctl__world : (N, F, 2) m, control-body positions at those times.
    """

    times: np.ndarray
    p_ctl__world: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def at(self, t) -> np.ndarray:
        """(len(t), F, D) positions at times t (s, clipped to the path's ends); D = 2,
        or 3 for the 3-D paths of tacest.sim3d.pokes."""
        t = np.asarray(t, float)
        N, F, D = self.p_ctl__world.shape
        out = np.empty((t.shape[0], F, D))
        for f in range(F):
            for c in range(D):
                out[:, f, c] = np.interp(t, self.times, self.p_ctl__world[:, f, c])
        return out


class _PathBuilder:
    def __init__(self, p0__world):
        self.times = [0.0]
        self.points = [np.array(p0__world, float)]

    def move(self, finger, target, duration=None, speed=TRANSIT_SPEED, others=None):
        """Move one finger to ``target`` (2,) in ``duration`` s or at ``speed``; the other
        fingers go to their ``others`` positions (F, 2) if given, else hold."""
        last = self.points[-1]
        new = last.copy() if others is None else np.array(others, float)
        new[finger] = target
        if duration is None:
            dist = float(np.max(np.linalg.norm(new - last, axis=1)))
            if dist < 1e-9:
                return
            duration = dist / speed
        self.times.append(self.times[-1] + duration)
        self.points.append(new)

    def build(self) -> Path:
        return Path(np.asarray(self.times), np.stack(self.points))


def poke_path(poke: Poke, p_ctl0__world, s_touch, object_top, finger_radius) -> tuple:
    """The control path of one poke (module docstring).

    p_ctl0__world : (F, 2) m, control positions at poke start; s_touch : m or None
    (the line misses the object); object_top : m, highest object point now;
    finger_radius : (F,) m.
    Returns ``(path, start (2,), end (2,))`` with the approach's start and end points.
    """
    d = poke.direction__world
    s = 0.0 if s_touch is None else float(s_touch)
    start = poke.target__world + d * (s + CLEARANCE)
    end = poke.target__world + d * (s - poke.depth)
    f = poke.finger
    p0 = np.array(p_ctl0__world, float)
    y_safe = object_top + float(np.max(finger_radius)) + SAFE_MARGIN
    # idle fingers lift out of the way; the poking finger goes up, across, down
    lifted = p0.copy()
    lifted[:, 1] = np.maximum(lifted[:, 1], y_safe)
    y_via = max(y_safe, p0[f, 1], start[1])
    b = _PathBuilder(p0)
    b.move(f, np.array([p0[f, 0], y_via]), others=np.where(np.arange(len(p0))[:, None] == f, p0, lifted))
    b.move(f, np.array([start[0], y_via]))
    b.move(f, start)
    b.move(f, end, duration=float(np.linalg.norm(start - end)) / poke.speed)
    b.move(f, start, duration=RETREAT_TIME)
    return b.build(), start, end

"""3-D pokes: the action parameterization and the fingertip paths that carry them out.

A 3-D poke is the vector (:data:`POKE3_NAMES`; /actions/params attrs kind = ``"poke"``,
``names`` as here)::

    [finger, approach_azimuth, approach_elevation, target_x, target_y, target_z, depth, speed]

- ``finger``: index of the fingertip that pokes (0-based);
- ``approach_azimuth`` (rad, any value) and ``approach_elevation`` (rad, in [0, π/2]):
  the direction FROM which the finger comes, world frame,
  ``d = (cos e·cos a, cos e·sin a, sin e)``: e = 0 is horizontal, from the side; e = π/2
  straight down from above; never from below the table.  Random pokes use e ~
  U(10°, 65°) (as the 2-D approach angle: steeper pushes only press the object onto the
  table, flatter ones drag the finger along it) and a ~ U(0, 2π);
- ``target_x, target_y, target_z``: m, world frame, the point it aims at (random pokes:
  the true volume centroid at poke start; planned pokes: the estimate's);
- ``depth``: m, how far the finger goes on past the point where it first touches the
  object; ``speed``: m/s along the approach line.

The path is the 2-D one (tacest.sim.pokes) in 3-D: transit up to a safe height above
the object, across, and down to the start point ``target + d·(s_touch + CLEARANCE)``;
approach to ``target + d·(s_touch − depth)`` at ``speed``; retreat to the start point
in RETREAT_TIME.  ``s_touch`` is where the finger sphere first touches the object in its
pose at poke start (tacest.sim3d.world.World3.touch_distance).

**Several fingers in one action.**  An action may move k distinct fingers at once: its
vector is k poke vectors one after another, named POKE3_NAMES and then the same names
with the suffix ``.1``, ``.2`` ... (:func:`action_names`; a plan file's ``/chosen/params``
and ``names``).  A reader that knows only POKE3_NAMES finds the first finger's poke.
The fingers go to their start points one after another, approach together (each at its
own speed and depth, starting at the same instant) and retreat together.  In a run file
each finger's poke is its own row of ``/actions/params`` (POKE3_NAMES) and the rows of
one action share their ``/actions/segments`` row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tacest.errors import TacestError
from tacest.sim.pokes import (APPROACH_TIME, CLEARANCE, DEPTH_LIMITS, POKE_KIND, POKE_STYLES, RANDOM_ANGLE_RANGE,
                              RANDOM_DEPTH_RANGE, RETREAT_TIME, SAFE_MARGIN, SPEED_LIMITS, Path, _PathBuilder,
                              draw_style)

__all__ = ["POKE3_NAMES", "POKE_KIND", "Poke3", "action_names", "pokes_from_vector", "random_poke", "poke_path",
           "Path"]

#: the parameter names of a 3-D poke (/actions/params attrs names)
POKE3_NAMES = ("finger", "approach_azimuth", "approach_elevation", "target_x", "target_y", "target_z",
               "depth", "speed")
#: random elevations, rad (the 2-D random approach angles above the horizontal)
RANDOM_ELEVATION_RANGE = RANDOM_ANGLE_RANGE


@dataclass
class Poke3:
    """One 3-D poke; see the module docstring.  target__world : (3,) m."""

    finger: int
    azimuth: float
    elevation: float
    target__world: np.ndarray
    depth: float
    speed: float

    @property
    def direction__world(self) -> np.ndarray:
        """(3,) unit vector from the target towards where the finger comes from."""
        ce = math.cos(self.elevation)
        return np.array([ce * math.cos(self.azimuth), ce * math.sin(self.azimuth), math.sin(self.elevation)])

    def approach_line(self, s_touch) -> tuple:
        """(start, end) (3,) m of the approach: ``target + d·(s + CLEARANCE)`` to
        ``target + d·(s − depth)``, s = s_touch m where the finger first touches along
        the line (None, the line misses the object: 0)."""
        d = self.direction__world
        s = 0.0 if s_touch is None else float(s_touch)
        return self.target__world + d * (s + CLEARANCE), self.target__world + d * (s - self.depth)

    def to_vector(self) -> np.ndarray:
        """(8,) in the order of POKE3_NAMES."""
        return np.array([self.finger, self.azimuth, self.elevation, *self.target__world, self.depth, self.speed],
                        float)

    @classmethod
    def from_vector(cls, vec, n_fingers: int, names=POKE3_NAMES) -> "Poke3":
        """A poke from a parameter vector whose entries are named ``names``.

        Checks every value (TacestError naming the bad one): finger index in range,
        elevation in [0, π/2], finite azimuth and target, depth in DEPTH_LIMITS, speed in
        [1e-3, 1] m/s.
        """
        names = [str(n) for n in names]
        vec = np.asarray(vec, float).reshape(-1)
        if len(names) != len(vec):
            raise TacestError(f"poke: {len(vec)} values for {len(names)} names")
        missing = [n for n in POKE3_NAMES if n not in names]
        if missing:
            raise TacestError(f"3-D poke: parameter(s) {', '.join(missing)} missing; a 3-D poke needs "
                              f"{', '.join(POKE3_NAMES)}")
        p = {n: float(vec[names.index(n)]) for n in POKE3_NAMES}
        for n, v in p.items():
            if not math.isfinite(v):
                raise TacestError(f"poke: {n} = {v} is not finite")
        f = p["finger"]
        if f != round(f) or not 0 <= f < n_fingers:
            raise TacestError(f"poke: finger = {f:g} is not a finger index in 0..{n_fingers - 1}")
        if not -1e-9 <= p["approach_elevation"] <= 0.5 * math.pi + 1e-9:
            raise TacestError(f"poke: approach_elevation = {p['approach_elevation']:.4g} rad is outside [0, π/2] "
                              "(the finger must come from above the ground)")
        lo, hi = DEPTH_LIMITS
        if not lo <= p["depth"] <= hi:
            raise TacestError(f"poke: depth = {p['depth']:.4g} m is outside [{lo}, {hi}] m")
        lo, hi = SPEED_LIMITS
        if not lo <= p["speed"] <= hi:
            raise TacestError(f"poke: speed = {p['speed']:.4g} m/s is outside [{lo}, {hi}] m/s")
        return cls(finger=int(round(f)), azimuth=p["approach_azimuth"], elevation=p["approach_elevation"],
                   target__world=np.array([p["target_x"], p["target_y"], p["target_z"]]), depth=p["depth"],
                   speed=p["speed"])


def action_names(k: int) -> tuple:
    """The names of an action of k fingers' pokes (module docstring): POKE3_NAMES, then
    POKE3_NAMES with the suffix ``.1`` ... ``.{k-1}``."""
    if int(k) < 1:
        raise TacestError(f"an action moves at least one finger, not {k}")
    return POKE3_NAMES + tuple(f"{n}.{j}" for j in range(1, int(k)) for n in POKE3_NAMES)


def pokes_from_vector(vec, n_fingers: int, names=None) -> list:
    """The pokes [Poke3] of one action whose vector ``vec`` has entries ``names``
    (default :func:`action_names` of len(vec) / 8): the first from the names of
    POKE3_NAMES, one more for each suffix ``.j`` (j = 1, 2, ...) whose whole set of
    names is present.  TacestError (naming the bad value) if a poke is bad or a finger
    moves twice."""
    vec = np.asarray(vec, float).reshape(-1)
    if names is None:
        if len(vec) % len(POKE3_NAMES):
            raise TacestError(f"an action of {len(vec)} values is not a whole number of 3-D pokes "
                              f"({len(POKE3_NAMES)} values each)")
        names = action_names(len(vec) // len(POKE3_NAMES))
    names = [str(n) for n in names]
    if len(names) != len(vec):
        raise TacestError(f"poke: {len(vec)} values for {len(names)} names")
    pokes = [Poke3.from_vector(vec, n_fingers, names)]
    j = 1
    while all(f"{n}.{j}" in names for n in POKE3_NAMES):
        cols = [names.index(f"{n}.{j}") for n in POKE3_NAMES]
        try:
            pokes.append(Poke3.from_vector(vec[cols], n_fingers))
        except TacestError as exc:
            raise TacestError(f"{exc} (the poke of suffix .{j})") from None
        j += 1
    fingers = [p.finger for p in pokes]
    if len(set(fingers)) != len(fingers):
        twice = sorted({f for f in fingers if fingers.count(f) > 1})
        raise TacestError(f"an action moves finger(s) {', '.join(map(str, twice))} twice; the fingers of one "
                          "action must differ")
    return pokes


def random_poke(rng: np.random.Generator, centroid__world, n_fingers: int, style: str = "gentle",
                vertices__world=None, ground_height: float = 0.0) -> Poke3:
    """A random poke of ``style`` (tacest.sim.pokes.POKE_STYLES or ``gentle``).

    gentle: at the object's centroid (3,) m, random finger, azimuth U(0, 2π), elevation
    U(10°, 65°), depth U(1, 3) cm, and the speed that makes the approach last
    APPROACH_TIME (1 s).  The other styles draw elevation, speed, depth (in sizes of the
    object whose vertices__world (K, 3) m are given), the target's height above
    ``ground_height`` (m) and its sideways offset across the approach from their
    PokeStyle, from any azimuth."""
    if style != "gentle":
        V = np.asarray(vertices__world, float)
        size = float(np.max(np.ptp(V, axis=0)))
        finger = int(rng.integers(n_fingers))
        azimuth = float(rng.uniform(0.0, 2.0 * math.pi))
        d = draw_style(POKE_STYLES[style], rng, size)
        top = float(np.max(V[:, 2]))
        side = np.array([-math.sin(azimuth), math.cos(azimuth), 0.0])  # horizontal, across the approach
        c = np.asarray(centroid__world, float)
        target = np.array([c[0], c[1], ground_height + d["height"] * (top - ground_height)]) + d["offset"] * size * side
        return Poke3(finger, azimuth, d["elevation"], target, d["depth"], d["speed"])
    finger = int(rng.integers(n_fingers))
    azimuth = float(rng.uniform(0.0, 2.0 * math.pi))
    elevation = float(rng.uniform(*RANDOM_ELEVATION_RANGE))
    depth = float(rng.uniform(*RANDOM_DEPTH_RANGE))
    return Poke3(finger, azimuth, elevation, np.asarray(centroid__world, float).copy(), depth,
                 (CLEARANCE + depth) / APPROACH_TIME)


def poke_path(poke, p_ctl0__world, s_touch, object_top, finger_radius) -> tuple:
    """The control path of one action (module docstring).

    poke : a Poke3, or a list of Poke3 of distinct fingers moving in one action;
    p_ctl0__world : (F, 3) m, control positions at the action's start; s_touch : m or
    None (the line misses the object), one per poke for a list; object_top : m, highest
    object point now; finger_radius : (F,) m.
    Returns ``(path (tacest.sim.pokes.Path with (N, F, 3) points), start, end)``: the
    approach's start and end points, (3,) for one Poke3, (k, 3) for a list of k.
    """
    single = isinstance(poke, Poke3)
    pokes = [poke] if single else list(poke)
    touches = [s_touch] if single else list(s_touch)
    starts, ends = (list(x) for x in zip(*(pk.approach_line(st) for pk, st in zip(pokes, touches))))
    p0 = np.array(p_ctl0__world, float)
    z_safe = object_top + float(np.max(finger_radius)) + SAFE_MARGIN
    # idle fingers lift out of the way; each poking finger in turn goes up, across, down
    lifted = p0.copy()
    lifted[:, 2] = np.maximum(lifted[:, 2], z_safe)
    b = _PathBuilder(p0)
    for j, (pk, start) in enumerate(zip(pokes, starts)):
        f = pk.finger
        now = b.points[-1][f]
        z_via = max(z_safe, now[2], start[2])
        if j == 0:
            b.move(f, np.array([now[0], now[1], z_via]), others=np.where(np.arange(len(p0))[:, None] == f, p0, lifted))
        else:
            b.move(f, np.array([now[0], now[1], z_via]))
        b.move(f, np.array([start[0], start[1], z_via]))
        b.move(f, start)
    # the approaches start together, each at its own speed; the retreats end together
    fingers = [pk.finger for pk in pokes]
    durations = [float(np.linalg.norm(a - e)) / pk.speed for pk, a, e in zip(pokes, starts, ends)]
    at_start = b.points[-1].copy()
    elapsed = 0.0
    for t_next in sorted(set(durations)):
        pos = b.points[-1].copy()
        for f, a, e, dur in zip(fingers, starts, ends, durations):
            pos[f] = e if t_next >= dur else a + (e - a) * (t_next / dur)
        b.move(fingers[0], pos[fingers[0]], duration=t_next - elapsed, others=pos)
        elapsed = t_next
    b.move(fingers[0], starts[0], duration=RETREAT_TIME, others=np.where(np.isin(np.arange(len(p0)), fingers)[:, None],
                                                                          at_start, b.points[-1]))
    path = b.build()
    if single:
        return path, starts[0], ends[0]
    return path, np.array(starts), np.array(ends)

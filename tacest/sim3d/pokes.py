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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tacest.errors import TacestError
from tacest.sim.pokes import (APPROACH_TIME, CLEARANCE, DEPTH_LIMITS, POKE_KIND, POKE_STYLES, RANDOM_ANGLE_RANGE,
                              RANDOM_DEPTH_RANGE, RETREAT_TIME, SAFE_MARGIN, SPEED_LIMITS, Path, _PathBuilder,
                              draw_style)

__all__ = ["POKE3_NAMES", "POKE_KIND", "Poke3", "random_poke", "poke_path", "Path"]

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


def poke_path(poke: Poke3, p_ctl0__world, s_touch, object_top, finger_radius) -> tuple:
    """The control path of one poke (module docstring).

    p_ctl0__world : (F, 3) m, control positions at poke start; s_touch : m or None
    (the line misses the object); object_top : m, highest object point now;
    finger_radius : (F,) m.
    Returns ``(path (tacest.sim.pokes.Path with (N, F, 3) points), start (3,), end (3,))``.
    """
    d = poke.direction__world
    s = 0.0 if s_touch is None else float(s_touch)
    start = poke.target__world + d * (s + CLEARANCE)
    end = poke.target__world + d * (s - poke.depth)
    f = poke.finger
    p0 = np.array(p_ctl0__world, float)
    z_safe = object_top + float(np.max(finger_radius)) + SAFE_MARGIN
    # idle fingers lift out of the way; the poking finger goes up, across, down
    lifted = p0.copy()
    lifted[:, 2] = np.maximum(lifted[:, 2], z_safe)
    z_via = max(z_safe, p0[f, 2], start[2])
    b = _PathBuilder(p0)
    b.move(f, np.array([p0[f, 0], p0[f, 1], z_via]), others=np.where(np.arange(len(p0))[:, None] == f, p0, lifted))
    b.move(f, np.array([start[0], start[1], z_via]))
    b.move(f, start)
    b.move(f, end, duration=float(np.linalg.norm(start - end)) / poke.speed)
    b.move(f, start, duration=RETREAT_TIME)
    return b.build(), start, end

"""The action space of ``tacest plan``: a 1 s poke toward the estimated centroid.

An action is a poke (tacest.sim.pokes, :data:`POKE_NAMES`) with its target at the
estimated centroid of the object now (the estimate's final pose of the last run).  The
planner chooses, per finger:

- ``approach_angle`` in :data:`ANGLE_RANGE` (10° .. 170°: from the right, from above, from
  the left; flatter approaches would drag the finger along the table).  Unlike the
  random pokes of the simulator (10°..65° and 115°..170°), steep pokes from above are
  allowed: they press on the top face, which is how the height of a box is felt;
- optionally (``vary``) ``depth`` in :data:`DEPTH_RANGE`, ``speed`` in
  :data:`SPEED_RANGE` and ``height`` in :data:`HEIGHT_RANGE` (the aim raised above the
  centroid by this fraction of the object's estimated height along the ground normal).
  Otherwise depth is :data:`DEFAULT_DEPTH` (the middle of the random pokes' range), the
  aim is the centroid and the speed makes the approach last :data:`APPROACH_TIME` (1 s),
  as the random pokes do;
- poke style ``dynamic`` (``tacest plan --poke-style dynamic``): depth, speed and
  height are always searched, the speed in :data:`DYNAMIC_SPEED_RANGE` (the simulators'
  fast pokes, 0.1-0.6 m/s) and the depth in :data:`DYNAMIC_DEPTH_RANGE` (2-12 cm): pokes
  that tip, topple and flick the object, as the dynamic pokes of ``tacest record
  --poke-style dynamic`` do.

In 3-D (:class:`ActionSpace3`, tacest.sim3d.pokes.POKE3_NAMES) the approach angle
becomes an approach direction: ``approach_azimuth`` in [-π, π] (any side) and
``approach_elevation`` in :data:`ELEVATION_RANGE` (10° .. 90°: from the side to straight
down onto the top face), with the same optional depth and speed.  An action may move
``fingers_per_action`` = k fingers at once (``tacest plan/explore --fingers-per-action
K``): the searched coordinates are k directions (each with its own optional depth,
speed and height: names suffixed ``.1`` ... for the second, third finger), each poked
by the nearest finger not yet taken, and the action's vector is the k pokes
(tacest.sim3d.pokes.action_names).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tacest.errors import TacestError
from tacest.sim.pokes import (APPROACH_TIME, CLEARANCE, POKE_NAMES, RANDOM_ANGLE_RANGE, RANDOM_DEPTH_RANGE,
                              check_fingers_per_action)

#: rad, approach angles the planner may choose (from the direction d = (cos a, sin a))
ANGLE_RANGE = (math.radians(10.0), math.radians(170.0))
#: m, depth past the first touch when it is not varied
DEFAULT_DEPTH = 0.5 * (RANDOM_DEPTH_RANGE[0] + RANDOM_DEPTH_RANGE[1])
#: m, depths the planner may choose with ``vary=("depth",)``
DEPTH_RANGE = (0.005, 0.04)
#: m/s, approach speeds the planner may choose with ``vary=("speed",)`` (0.6 .. 3 s
#: approaches at the default depth)
SPEED_RANGE = (0.02, 0.1)
#: m/s, approach speeds of the ``dynamic`` poke style (tacest.sim.pokes' fast pokes)
DYNAMIC_SPEED_RANGE = (0.1, 0.6)
#: m, depths past the first touch of the ``dynamic`` poke style: the simulators' fast and
#: high pokes push 0.3-1.5 object sizes in (3-15 cm on a 10 cm box); the planner may
#: choose up to 12 cm
DYNAMIC_DEPTH_RANGE = (0.02, 0.12)
#: fractions of the object's estimated height (along the ground normal) the aim may be
#: raised above its centroid with ``vary=("height",)``: up to the simulators' high pokes
#: (25-45 % above a box's centre tips and topples it on a grippy ground)
HEIGHT_RANGE = (0.0, 0.45)
VARIABLES = ("depth", "speed", "height")
#: poke styles of the action space (module docstring)
ACTION_STYLES = ("gentle", "dynamic")
#: rad, 3-D approach elevations the planner may choose (0: horizontal; flatter than 10°
#: the finger would drag along the table; 90°: straight down onto the top face)
ELEVATION_RANGE = (math.radians(10.0), math.radians(90.0))
#: rad, 3-D approach azimuths (every side of the object)
AZIMUTH_RANGE = (-math.pi, math.pi)
#: m, how far out along the approach line the nearest finger is looked for (about an
#: object's size: where the approach of a poke starts)
APPROACH_REACH = 0.1


@dataclass
class ActionSpace:
    """What the planner chooses (module docstring).  vary : subset of VARIABLES; style :
    ``gentle`` or ``dynamic`` (adds depth, speed and height, in the dynamic ranges);
    object_height : m, the object's estimated extent along ``up`` (D,), the ground
    normal (the unit of ``height``)."""

    n_fingers: int = 1
    vary: tuple = field(default_factory=tuple)
    angle_range: tuple = ANGLE_RANGE
    depth: float = DEFAULT_DEPTH
    style: str = "gentle"
    object_height: float = 0.0
    up: np.ndarray | None = None

    def __post_init__(self):
        bad = [v for v in self.vary if v not in VARIABLES]
        if bad:
            raise TacestError(f"cannot vary {', '.join(bad)}: choose from {', '.join(VARIABLES)}")
        if self.style not in ACTION_STYLES:
            raise TacestError(f"unknown poke style {self.style!r}: use {', '.join(ACTION_STYLES)}")
        vary = set(self.vary) | ({"depth", "speed", "height"} if self.style == "dynamic" else set())
        self.vary = tuple(v for v in VARIABLES if v in vary)
        if "height" in self.vary and (self.up is None or not self.object_height > 0):
            raise TacestError("varying the aim's height needs the object's height and the ground normal")

    def range_of(self, name: str) -> tuple:
        """(low, high) of a searched variable besides the direction."""
        if name == "depth":
            return DYNAMIC_DEPTH_RANGE if self.style == "dynamic" else DEPTH_RANGE
        if name == "speed":
            return DYNAMIC_SPEED_RANGE if self.style == "dynamic" else SPEED_RANGE
        return HEIGHT_RANGE

    @property
    def finger_names(self) -> list:
        """Names of one finger's searched coordinates (direction first)."""
        return ["approach_angle", *self.vary]

    @property
    def names(self) -> list:
        """Names of the searched coordinates (angle first)."""
        return self.finger_names

    def bounds(self):
        lo, hi = self._direction_bounds()
        for v in self.vary:
            r = self.range_of(v)
            lo.append(r[0])
            hi.append(r[1])
        return np.array(lo), np.array(hi)

    def _direction_bounds(self):
        return [self.angle_range[0]], [self.angle_range[1]]

    def searched_fingers(self) -> list:
        """The fingers the planner searches one by one (each its own search)."""
        return list(range(self.n_fingers))

    @property
    def finger_poke_names(self) -> tuple:
        """The names of one finger's poke vector."""
        return POKE_NAMES

    @property
    def poke_names(self) -> tuple:
        """The names of an action's vector (the plan file's names)."""
        return self.finger_poke_names

    def action(self, finger: int, u, target__world) -> np.ndarray:
        """Poke vector (:attr:`poke_names`) of searched coordinates u aimed at target (D,) m."""
        u = np.asarray(u, float).reshape(-1)
        vals = dict(zip(self.finger_names, u))
        depth = float(vals.get("depth", self.depth))
        speed = float(vals.get("speed", (CLEARANCE + depth) / APPROACH_TIME))
        t = np.asarray(target__world, float)
        if "height" in vals:  # the aim raised along the ground normal
            t = t + float(vals.pop("height")) * self.object_height * np.asarray(self.up, float)
        named = {**vals, "finger": finger, "depth": depth, "speed": speed,
                 **{f"target_{c}": float(v) for c, v in zip("xyz", t)}}
        return np.array([named[n] for n in self.finger_poke_names], float)

    def _random_direction(self, rng: np.random.Generator) -> list:
        angle = float(rng.uniform(*RANDOM_ANGLE_RANGE))
        if rng.random() < 0.5:
            angle = math.pi - angle
        return [angle]

    def random_action(self, rng: np.random.Generator, target__world) -> np.ndarray:
        """The random baseline: a random finger and approach angle, as the simulator's
        random pokes draw it (U(10°, 65°) from the right or its mirror from the left);
        depth, speed and height as :meth:`action` (uniform within their ranges if varied)."""
        finger = int(rng.integers(self.n_fingers))
        return self.action(finger, self._random_coordinates(rng), target__world)

    def _random_coordinates(self, rng: np.random.Generator) -> list:
        """One finger's random searched coordinates: a random direction, then each varied
        variable uniform within its range."""
        return self._random_direction(rng) + [float(rng.uniform(*self.range_of(v))) for v in self.vary]


@dataclass
class ActionSpace3(ActionSpace):
    """The 3-D action space (module docstring): approach azimuth and elevation per
    finger, optionally depth and speed; poke vectors of tacest.sim3d.pokes.POKE3_NAMES,
    or with ``fingers_per_action`` = k > 1 actions of k fingers' pokes at once
    (tacest.sim3d.pokes.action_names)."""

    elevation_range: tuple = ELEVATION_RANGE
    #: (F, 3) m, the fingertips now; given, one search covers every finger: a direction
    #: is poked by the finger nearest its approach (:meth:`nearest_finger`)
    p_finger__world: np.ndarray | None = None
    #: fingers moving in one action (1 .. n_fingers)
    fingers_per_action: int = 1

    def __post_init__(self):
        super().__post_init__()
        k = check_fingers_per_action(self.fingers_per_action, self.n_fingers, 3)
        if k > 1 and self.p_finger__world is None:
            raise TacestError("several fingers per action need the fingertips' positions")
        self.fingers_per_action = k

    def searched_fingers(self) -> list:
        """[None] (one search, the nearest finger per direction) when the fingertips are
        known: the fingers are alike and the idle ones are parked above the object, so
        the same direction informs the same whichever finger pokes; else each finger."""
        return [None] if self.p_finger__world is not None else super().searched_fingers()

    def nearest_finger(self, u, target__world, taken=()) -> int:
        """The finger, not in ``taken``, nearest the approach line's point APPROACH_REACH
        out from the target (the shortest transit to the poke's start)."""
        az, el = float(u[0]), float(u[1])
        d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        start = np.asarray(target__world, float) + APPROACH_REACH * d
        dist = np.linalg.norm(np.asarray(self.p_finger__world, float) - start, axis=1)
        dist[list(taken)] = np.inf
        return int(np.argmin(dist))

    def action(self, finger, u, target__world) -> np.ndarray:
        """As ActionSpace.action; finger None: :meth:`nearest_finger`.  With k fingers per
        action u holds k fingers' coordinates one after another (:attr:`names`); each
        takes the nearest finger not taken by the ones before it (``finger`` is then
        ignored) and the vector is their k pokes."""
        u = np.asarray(u, float).reshape(-1)
        if self.fingers_per_action == 1:
            if finger is None:
                finger = self.nearest_finger(u, target__world)
            return super().action(finger, u, target__world)
        n, taken, out = len(self.finger_names), [], []
        for j in range(self.fingers_per_action):
            uj = u[j * n:(j + 1) * n]
            taken.append(self.nearest_finger(uj, target__world, taken))
            out.append(super().action(taken[-1], uj, target__world))
        return np.concatenate(out)

    @property
    def finger_names(self) -> list:
        return ["approach_azimuth", "approach_elevation", *self.vary]

    @property
    def names(self) -> list:
        """Names of the searched coordinates: one finger's :attr:`finger_names`, then
        those of the other fingers of an action, suffixed ``.1``, ``.2`` ..."""
        one = self.finger_names
        return one + [f"{n}.{j}" for j in range(1, self.fingers_per_action) for n in one]

    @property
    def finger_poke_names(self) -> tuple:
        from tacest.sim3d.pokes import POKE3_NAMES

        return POKE3_NAMES

    @property
    def poke_names(self) -> tuple:
        from tacest.sim3d.pokes import action_names

        return action_names(self.fingers_per_action)

    def bounds(self):
        lo, hi = super().bounds()
        return np.tile(lo, self.fingers_per_action), np.tile(hi, self.fingers_per_action)

    def _direction_bounds(self):
        return [AZIMUTH_RANGE[0], self.elevation_range[0]], [AZIMUTH_RANGE[1], self.elevation_range[1]]

    def _random_direction(self, rng: np.random.Generator) -> list:
        """As the 3-D simulator's random pokes: azimuth U(-π, π), elevation U(10°, 65°)."""
        return [float(rng.uniform(*AZIMUTH_RANGE)), float(rng.uniform(*RANDOM_ANGLE_RANGE))]

    def random_action(self, rng: np.random.Generator, target__world) -> np.ndarray:
        """As ActionSpace.random_action; with k fingers per action, k distinct random
        fingers, each with its own random direction (and depth, speed, height)."""
        if self.fingers_per_action == 1:
            return super().random_action(rng, target__world)
        fingers = rng.choice(self.n_fingers, self.fingers_per_action, replace=False)
        out = []
        for f in fingers:
            out.append(super().action(int(f), self._random_coordinates(rng), target__world))
        return np.concatenate(out)


def split_action(action: dict) -> list:
    """The per-finger pokes of an action {name: value} (a plan's chosen_dict): the names
    without a suffix, then those with ``.1``, ``.2`` ... (tacest.sim3d.pokes.action_names),
    each as a dict of the unsuffixed names."""
    first = {k: v for k, v in action.items() if "." not in k}
    out, j = [first], 1
    while f"finger.{j}" in action:
        out.append({k[: -len(f".{j}")]: v for k, v in action.items() if k.endswith(f".{j}")})
        j += 1
    return out


def describe_action(action: dict, detailed: bool = False) -> str:
    """An action {name: value} (a plan's chosen_dict) in words, its fingers' pokes joined
    by ``+`` (3-D) — short: ``approach 35 deg`` (2-D), ``finger 1 from azimuth 40 deg,
    elevation 30 deg`` (3-D); ``detailed``: each poke's finger, approach to 0.1 deg,
    target (m), depth (mm) and speed (mm/s)."""
    parts = []
    for x in split_action(action):
        if "approach_angle" in x:
            towards = f"approach {math.degrees(x['approach_angle']):.{1 if detailed else 0}f} deg"
        elif detailed:
            towards = (f"approach azimuth {math.degrees(x['approach_azimuth']):.1f} deg, elevation "
                       f"{math.degrees(x['approach_elevation']):.1f} deg")
        else:
            towards = (f"from azimuth {math.degrees(x['approach_azimuth']):.0f} deg, elevation "
                       f"{math.degrees(x['approach_elevation']):.0f} deg")
        if not detailed:
            parts.append(towards if "approach_angle" in x else f"finger {int(x['finger'])} {towards}")
            continue
        target = ", ".join(f"{x[k]:.4f}" for k in ("target_x", "target_y", "target_z") if k in x)
        parts.append(f"finger {int(x['finger'])}, {towards} toward ({target}) m, depth {1e3 * x['depth']:.0f} mm, "
                     f"speed {1e3 * x['speed']:.0f} mm/s")
    return ("; " if detailed else " + ").join(parts)


def object_height(model) -> float:
    """m: the estimated object's extent along the ground normal now (a planning
    ModelState or ModelState3: vertices in the body frame, pose, up)."""
    from tacest.geometry.transforms import transform_points

    V = np.asarray(model.vertices, float)
    Vw = transform_points(np.asarray(model.pose, float), V, V.shape[1])
    return float(np.ptp(Vw @ np.asarray(model.up, float)))


def action_space_for(model, style: str = "gentle", vary=(), fingers_per_action: int = 1) -> ActionSpace:
    """The action space of a planning model state (ModelState: :class:`ActionSpace`;
    ModelState3: :class:`ActionSpace3` over its fingertips), poke style ``style``,
    ``fingers_per_action`` fingers moving in one action (3-D only)."""
    shared = dict(n_fingers=model.n_fingers, vary=tuple(vary), style=style, object_height=object_height(model),
                  up=np.asarray(model.up, float))
    if np.asarray(model.up).shape[0] == 3:
        return ActionSpace3(p_finger__world=model.p_finger__world, fingers_per_action=int(fingers_per_action),
                            **shared)
    check_fingers_per_action(fingers_per_action, model.n_fingers, 2)
    return ActionSpace(**shared)

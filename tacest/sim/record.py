"""Simulated recordings (``tacest record --source sim``, 2-D): pokes in the pymunk world,
the tactile sensor model, and run files per SPEC.

Public API::

    SimOptions                                   recorder settings (the CLI's options)
    WorldState                                   object, its state, fingers, effects
    initial_state(opts) -> WorldState a new object at rest on the ground
    toss_state(state, rng) -> WorldState        the object released in the air (a toss)
    state_at_rest(obj, x=0, angle=None, fingers=1, finger_radius=0.01, effects=()) -> WorldState
    simulate_pokes(state, actions, opts=None, names=POKE_NAMES) -> Run
    record_sim(opts, plan_path=None, append_to=None) -> Run
    state_from_run(run) -> WorldState            continue from a run's last truth state
    append_run(old, new) -> Run                  concatenate a continuation
    simulate_aimed_pokes(aim, n, opts, state=None, run=None) -> Run
                                                 pokes aimed one at a time at the object as it is

Per sample interval (time[k-1], time[k]] (docs/simulation.md): contact = the finger
touched the object in any physics substep; force = the summed substep impulses of the
finger on the object / dt (N, world frame); normal = the impulse-weighted mean contact
normal, unit, pointing out of the object into the finger.  Sample 0 is the state at
the start (no interval: no contact).  Then the sensor model: force gain
(``force_scale``), noise (on contact samples only, so a clean sensor reads exactly 0
off contact), offset (``force_bias``, every sample), delay (``latency``), clock
(``time_scale``).  Positions get noise on every sample.

Randomness: the object, the effects' parameters, the pokes and the noise each draw
from their own stream of ``seed``, so changing one (adding an effect, another noise
level) leaves the others as they were.
"""

from __future__ import annotations

import logging

import json
import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from tacest.errors import TacestError
from tacest.interrupt import deferred_interrupts
from tacest.io.run import Actions, Run, Truth
from tacest.sim import effects as fx
from tacest.geometry.polygon import signed_area
from tacest.geometry.transforms import rot2
from tacest.sim.objects import (SimObject, apply_com_offset, inradius, make_shape, rest_angle, resting_pose,
                                uniform_object)
from tacest.sim.pokes import (POKE_KIND, POKE_NAMES, Poke, check_fingers_per_action, check_poke_style, poke_path,
                              random_poke, style_of_poke)
from tacest.sim.world import GRAVITY, MAX_FINGER_FORCE, MAX_SUBSTEP, World

log = logging.getLogger(__name__)

#: s, unrecorded settling of a new object on the ground before sample 0
PRE_ROLL = 0.5
#: s, the fingers hold still this long after the last poke (the object comes to rest)
SETTLE_TIME = 0.3
#: s, longest wait after a poke for the object to come to rest
REST_WAIT = 2.0
#: at rest: speed below this (m/s) and angular speed below REST_OMEGA (rad/s)
REST_SPEED = 2e-3
REST_OMEGA = 0.05
#: s, length of a recording without pokes
EMPTY_TIME = 1.0
#: m, park height of the fingers above the object's top at the start
PARK_HEIGHT = 0.05
#: m, horizontal spacing of parked fingers
PARK_SPACING = 0.06
#: m, lever arm that turns --observe-pose SIGMA (m) into an angle sigma (SIGMA / lever)
POSE_ANGLE_LEVER = 0.05
#: m, the loose size bound written to /prior (every simulated object is smaller)
SIZE_BOUND = 0.3
#: a toss (``SimOptions.toss``, ``tacest record --toss``): the robot lets go of the
#: object in the air, from a random release drawn from these ranges: the lowest vertex
#: TOSS_DROP m above the ground, horizontal speed TOSS_SPEED m/s either way, upward
#: speed TOSS_LIFT m/s, spin TOSS_SPIN rad/s either way, any orientation.  The flight
#: lasts 0.1-0.3 s, long enough for gravity, drag and spin decay to show in pose
#: observations, and the landing is an impact of 1-2 m/s (docs/simulation.md, "Tosses")
TOSS_DROP = (0.10, 0.25)
TOSS_SPEED = (0.1, 0.5)
TOSS_LIFT = (0.5, 1.0)
TOSS_SPIN = (2.0, 10.0)
#: s, longest wait for a tossed object to come to rest before the first poke (or the end)
TOSS_WAIT = 3.0

# independent random streams of one seed
_STREAM_OBJECT, _STREAM_POKES, _STREAM_NOISE, _STREAM_TOSS = 1, 2, 3, 4


def _rng(seed, stream, *more) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), stream, *map(int, more)]))


@dataclass
class SimOptions:
    """Settings of a simulated recording (one field per ``tacest record`` option).

    dim : 2, or 3 for the MuJoCo world of tacest.sim3d (record_sim dispatches);
    object_spec : ``box``, ``box:W,H``, ``polygon``, ``polygon:K`` or a vertex file
    (tacest.sim.objects; 3-D: tacest.sim3d.objects); seed : int >= 0; pokes : number
    of random pokes; fingers : number of fingertips; effects : list of
    ``NAME[:key=value,...]`` strings or Effect objects; noise_force : N, noise_position :
    m, noise_normal : rad (one sigma); force_stream : write /tactile/force;
    observe_pose : m, write /observations/pose with this position sigma (None: don't);
    toss : start with the object tossed (:func:`toss_state`) instead of at rest;
    dt : s, sample period; finger_radius : m; substeps : minimum physics substeps per
    sample (more when dt / substeps > MAX_SUBSTEP); max_finger_force : N, finger drive limit;
    poke_style : how random pokes are drawn (tacest.sim.pokes.POKE_MIXES: ``gentle``, the
    dynamic ``fast``, ``high``, ``flick``, their mix ``dynamic``, or ``mixed``);
    fingers_per_action : 3-D only: each random action moves this many distinct fingers
    together, each with its own random poke of the action's style (tacest.sim3d.pokes).
    """

    dim: int = 2
    object_spec: str = "box"
    seed: int = 0
    pokes: int = 6
    fingers: int = 1
    effects: list = field(default_factory=list)
    noise_force: float = 0.02
    noise_position: float = 1e-4
    noise_normal: float = 0.02
    force_stream: bool = True
    observe_pose: Optional[float] = None
    toss: bool = False
    dt: float = 0.01
    finger_radius: float = 0.01
    substeps: int = 20
    max_finger_force: float = MAX_FINGER_FORCE
    poke_style: str = "gentle"
    fingers_per_action: int = 1

    def validate(self) -> "SimOptions":
        """Raise TacestError for any value the simulator cannot use."""
        if int(self.dim) not in (2, 3):
            raise TacestError(f"--dim must be 2 or 3, got {self.dim}")
        if int(self.seed) < 0:
            raise TacestError(f"--seed must be >= 0, got {self.seed}")
        if int(self.pokes) < 0:
            raise TacestError(f"--pokes must be >= 0, got {self.pokes}")
        check_poke_style(self.poke_style)
        if int(self.fingers) < 1:
            raise TacestError(f"--fingers must be >= 1, got {self.fingers}")
        check_fingers_per_action(self.fingers_per_action, self.fingers, self.dim)
        for name in ("noise_force", "noise_position", "noise_normal"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise TacestError(f"--{name.replace('_', '-')} must be >= 0, got {v}")
        if self.observe_pose is not None and not (math.isfinite(self.observe_pose) and self.observe_pose >= 0):
            raise TacestError(f"--observe-pose must be >= 0, got {self.observe_pose}")
        if not (math.isfinite(self.dt) and 1e-4 <= self.dt <= 0.1):
            raise TacestError(f"--dt must be in [1e-4, 0.1] s, got {self.dt}")
        if not (0.001 <= self.finger_radius <= 0.05):
            raise TacestError(f"finger radius must be in [0.001, 0.05] m, got {self.finger_radius}")
        if int(self.substeps) < 1 or not self.max_finger_force > 0:
            raise TacestError("substeps must be >= 1 and max_finger_force > 0")
        return self

    @property
    def n_substeps(self) -> int:
        """Physics substeps per sample: at least ``substeps``, and h <= MAX_SUBSTEP."""
        return max(int(self.substeps), int(math.ceil(self.dt / MAX_SUBSTEP - 1e-9)))


@dataclass
class WorldState:
    """Everything needed to continue a simulation.

    obj : SimObject; pose : (3,) [x m, y m, angle rad] of the COM; velocity : (3,)
    [vx, vy m/s, omega rad/s]; p_finger__world : (F, 2) m; finger_radius : (F,) m;
    effects : list of resolved Effect (all of them, sensor and clock ones included);
    time : s, true time of this state; ground_state : (2,) [y m, vy m/s] of the
    soft_contact plate.
    """

    obj: SimObject
    pose: np.ndarray
    velocity: np.ndarray
    p_finger__world: np.ndarray
    finger_radius: np.ndarray
    effects: list = field(default_factory=list)
    time: float = 0.0
    ground_state: np.ndarray = field(default_factory=lambda: np.zeros(2))

    @property
    def n_fingers(self) -> int:
        return int(len(self.p_finger__world))

    def world(self, max_finger_force=MAX_FINGER_FORCE) -> World:
        """A pymunk World in this state."""
        return World(self.obj, self.pose, self.velocity, self.p_finger__world, self.finger_radius,
                     self.effects, ground_state=self.ground_state, max_finger_force=max_finger_force)

    @classmethod
    def of(cls, world: World, effects, time) -> "WorldState":
        return cls(obj=world.obj, pose=world.pose, velocity=world.velocity,
                   p_finger__world=world.p_finger__world, finger_radius=world.finger_radius.copy(),
                   effects=list(effects), time=float(time), ground_state=world.ground_state)


# ---------------------------------------------------------------------------------
# a new object


def effect_context(obj: SimObject) -> fx.EffectContext:
    """What the effects' random draws depend on, for a 2-D object (mass kg, inertia
    kg·m² about the COM, inradius m about the centroid, faces, ground friction)."""
    return fx.EffectContext(mass=obj.mass, inertia=obj.inertia, inradius=inradius(obj.vertices),
                            n_faces=obj.n_faces, friction_ground=obj.friction_ground)


@deferred_interrupts()  # Ctrl-C in a substep's cffi callback would be lost (tacest.interrupt)
def initial_state(opts: SimOptions) -> WorldState:
    """A new object (per ``opts.object_spec`` and ``opts.seed``) at rest on the ground,
    with its effects resolved and the fingers parked above it.

    Draw order in the object stream: shape, mass, frictions, rest face.  Effects draw
    from their own streams (tacest.sim.effects.resolve_effects); ``com_offset`` moves
    the COM before the rest face is chosen.  The world settles for PRE_ROLL s
    (unrecorded) so sample 0 is at rest.
    """
    opts.validate()
    rng = _rng(opts.seed, _STREAM_OBJECT)
    vertices, kind, preferred = make_shape(opts.object_spec, rng)
    obj = uniform_object(vertices, kind, rng)
    effects = fx.resolve_effects(opts.effects, opts.seed, effect_context(obj))
    com = fx.find(effects, "com_offset")
    if com is not None:
        obj = apply_com_offset(obj, com["dx"], com["dy"])
    angle = rest_angle(obj.vertices, rng, preferred)
    state = state_at_rest(obj, angle=angle, fingers=int(opts.fingers), finger_radius=opts.finger_radius,
                          effects=effects)
    log.info(f"object: {kind}, settling on the ground")  # no parameters: the truth may be hidden
    world = state.world(opts.max_finger_force)
    h = opts.dt / opts.n_substeps
    hold = world.p_control__world
    for _ in range(int(round(PRE_ROLL / h))):
        world.step(hold, h)
    world.take_measurement()
    settled = WorldState.of(world, effects, 0.0)
    settled.velocity = np.zeros(3)
    return settled


def _static_ground(obj, effects) -> np.ndarray:
    """(2,) [y, vy] of the soft_contact plate carrying the object's weight (zeros if rigid)."""
    soft = fx.find(effects, "soft_contact")
    if soft is None:
        return np.zeros(2)
    return np.array([-obj.mass * GRAVITY / soft["stiffness"], 0.0])


def state_at_rest(obj: SimObject, x=0.0, angle=None, fingers=1, finger_radius=0.01, effects=()) -> WorldState:
    """``obj`` resting on the ground with its COM at horizontal ``x`` (m), fingers parked.

    angle : rad, or None for the stable resting orientation nearest to 0;
    fingers : number of fingertips, parked PARK_HEIGHT above the object's top, spaced
    PARK_SPACING apart; finger_radius : m; effects : resolved Effects (a soft_contact
    ground starts sunk by the object's weight).  Not settled: the solver's first steps
    take up the contact slop (~1e-4 m).
    """
    if angle is None:
        angle = rest_angle(obj.vertices, None, preferred=0.0)
    effects = list(effects)
    pose = resting_pose(obj.vertices, angle, x=x)
    top = float(np.max((obj.vertices @ rot2(angle).T)[:, 1])) + pose[1]
    ground = _static_ground(obj, effects)  # the object starts sunk into a soft ground
    pose = pose + np.array([0.0, ground[0], 0.0])
    return WorldState(obj=obj, pose=pose, velocity=np.zeros(3), p_finger__world=park_fingers(x, top, fingers, finger_radius),
                      finger_radius=np.full(int(fingers), float(finger_radius)), effects=effects, ground_state=ground)


def park_fingers(x: float, top: float, fingers: int, finger_radius: float) -> np.ndarray:
    """(F, 2) m: F fingertips of ``finger_radius`` m parked PARK_HEIGHT above the height
    ``top`` (m, the highest point the object reaches), PARK_SPACING apart about ``x`` (m)."""
    F = int(fingers)
    return np.stack([x + (np.arange(F) - 0.5 * (F - 1)) * PARK_SPACING,
                     np.full(F, top + finger_radius + PARK_HEIGHT)], axis=1)


def toss_state(state: WorldState, rng: np.random.Generator, x: float = None) -> WorldState:
    """``state``'s object released in the air, as by a robot that lets go of it: at a
    random orientation with its lowest vertex TOSS_DROP above the ground, its COM at
    horizontal ``x`` (m; default: where it is now), moving at TOSS_SPEED sideways and TOSS_LIFT upwards and
    spinning at TOSS_SPIN (each drawn from ``rng``, the sideways and spin senses at
    random).  The fingers are parked above the highest point any vertex can reach in
    the flight; a soft ground starts unloaded."""
    obj = state.obj
    angle = float(rng.uniform(-math.pi, math.pi))
    drop = float(rng.uniform(*TOSS_DROP))
    vx = float(rng.uniform(*TOSS_SPEED)) * (1.0 if rng.random() < 0.5 else -1.0)
    vy = float(rng.uniform(*TOSS_LIFT))
    omega = float(rng.uniform(*TOSS_SPIN)) * (1.0 if rng.random() < 0.5 else -1.0)
    x = float(state.pose[0] if x is None else x)
    pose = resting_pose(obj.vertices, angle, x=x) + np.array([0.0, drop, 0.0])
    reach = float(np.max(np.linalg.norm(obj.vertices, axis=1)))  # any vertex, any angle
    top = pose[1] + vy * vy / (2.0 * GRAVITY) + reach
    radius = np.asarray(state.finger_radius, float)
    return WorldState(obj=obj, pose=pose, velocity=np.array([vx, vy, omega]),
                      p_finger__world=park_fingers(x, top, len(radius), float(np.max(radius))),
                      finger_radius=radius.copy(), effects=list(state.effects), time=state.time,
                      ground_state=np.zeros(2))


# ---------------------------------------------------------------------------------
# simulating pokes


@dataclass
class _Trajectory:
    """True (noise-free) series of a simulation: T samples, F fingers."""

    t_true: np.ndarray  # (T,) s
    p_finger__world: np.ndarray  # (T, F, 2) m
    contact: np.ndarray  # (T, F) bool
    impulse__world: np.ndarray  # (T, F, 2) N·s on the object
    normal__world: np.ndarray  # (T, F, 2) unit or NaN
    pose: np.ndarray  # (T, 3) COM pose
    segments: np.ndarray  # (A, 2) int
    params: np.ndarray  # (A, 6)
    final: WorldState


def _at_rest(velocity) -> bool:
    return math.hypot(velocity[0], velocity[1]) < REST_SPEED and abs(velocity[2]) < REST_OMEGA


@deferred_interrupts()  # Ctrl-C in a substep's cffi callback would be lost (tacest.interrupt)
def _simulate(state: WorldState, sources, opts: SimOptions, rng_pokes, lead_idle=False,
              settle_first=False) -> _Trajectory:
    """Run the pokes ``sources`` (each a (6,) POKE_NAMES vector or None for a random
    poke) from ``state``.  Every poke but the first (and the first too with
    ``lead_idle``) starts after one idle sample interval, so segments tile the run.
    With ``settle_first`` (a toss) the fingers first hold still until the object has
    come to rest (at most TOSS_WAIT s; then SETTLE_TIME more when there are no pokes):
    those samples belong to no action."""
    world = state.world(opts.max_finger_force)
    F = world.n_fingers
    dt = float(opts.dt)
    n_sub = opts.n_substeps
    h = dt / n_sub
    cols = {k: [] for k in ("p", "c", "j", "n", "q")}

    def record(m=None):
        cols["p"].append(world.p_finger__world)
        cols["q"].append(world.pose)
        if m is None:
            cols["c"].append(np.zeros(F, bool))
            cols["j"].append(np.zeros((F, 2)))
            cols["n"].append(np.full((F, 2), np.nan))
        else:
            cols["c"].append(m.contact)
            cols["j"].append(m.impulse__world)
            cols["n"].append(m.normal__world)

    def hold(n_samples):
        p = world.p_control__world
        for _ in range(n_samples):
            for _ in range(n_sub):
                world.step(p, h)
            record(world.take_measurement())

    def hold_until_rest(limit_s):
        for _ in range(int(round(limit_s / dt))):
            if _at_rest(world.velocity):
                return
            hold(1)

    record()
    segments, params = [], []
    A = len(sources)
    if settle_first:
        log.info("tossed: waiting for the object to come to rest")
        hold_until_rest(TOSS_WAIT)
    for i, src in enumerate(sources):
        log.info(f"poke {i + 1}/{A}")
        if i > 0 or lead_idle:
            hold(1)
        start = len(cols["q"]) - 1
        if src is None:
            poke = random_poke(rng_pokes, world.centroid__world(), F, style_of_poke(opts.poke_style, rng_pokes, i),
                               world.vertices__world())
        else:
            poke = Poke.from_vector(src, F)
        reach = SIZE_BOUND + float(np.max(world.finger_radius))
        s = world.touch_distance(poke.target__world - reach * poke.direction__world, poke.direction__world,
                                 world.finger_radius[poke.finger], reach=2 * reach)
        s_touch = None if s is None else s - reach
        top = float(np.max(world.vertices__world()[:, 1]))
        path, _, _ = poke_path(poke, world.p_control__world, s_touch, top, world.finger_radius)
        extra = SETTLE_TIME if i == A - 1 else 0.0
        n_samples = int(math.ceil((path.duration + extra) / dt - 1e-9))
        ctl = path.at(h * np.arange(1, n_samples * n_sub + 1))
        for k in range(n_samples):
            for j in range(n_sub):
                world.step(ctl[k * n_sub + j], h)
            record(world.take_measurement())
        # like a robot, wait until the object has stopped (a tipped object may still fall)
        hold_until_rest(REST_WAIT)
        segments.append((start, len(cols["q"])))
        params.append(poke.to_vector())
    if A == 0:
        hold(int(round((SETTLE_TIME if settle_first else EMPTY_TIME) / dt)))
    T = len(cols["q"])
    t_true = state.time + dt * np.arange(T)
    return _Trajectory(
        t_true=t_true, p_finger__world=np.array(cols["p"]), contact=np.array(cols["c"]),
        impulse__world=np.array(cols["j"]), normal__world=np.array(cols["n"]), pose=np.array(cols["q"]),
        segments=np.array(segments, np.int64).reshape(-1, 2), params=np.array(params, float).reshape(-1, 6),
        final=WorldState.of(world, state.effects, t_true[-1]))


# ---------------------------------------------------------------------------------
# the sensor model


def _rotate(v, angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _tilt(n, w):
    """Unit vectors ``n`` (..., 3) rotated by the part of the rotation vectors ``w``
    (..., 3) (rad) perpendicular to them: a tilt by |w_perp| rad, exact for any size."""
    w_perp = w - np.sum(w * n, axis=-1, keepdims=True) * n
    theta = np.linalg.norm(w_perp, axis=-1, keepdims=True)
    return np.cos(theta) * n + np.sinc(theta / np.pi) * np.cross(w_perp, n)


def sensor_streams(traj_contact, traj_impulse, traj_normal, dt_true, effects, noise_force, noise_normal, rng):
    """The measured tactile streams from the true ones, in 2-D or 3-D (D = 2 or 3).

    traj_contact : (T, F) bool; traj_impulse : (T, F, D) N·s on the object per
    interval; traj_normal : (T, F, D) unit or NaN; dt_true : s.
    Returns ``(contact (T, F) uint8, force (T, F, D) N, normal (T, F, D))``:
    force = gain·impulse/dt + noise (contact samples) + bias (every sample; force_bias
    fx, fy and in 3-D fz); the normal rotated by N(0, noise_normal) rad (3-D: tilted
    by a rotation whose two components perpendicular to it are N(0, noise_normal)
    rad each); then everything delayed by ``latency`` samples (the first samples read
    no contact, force = bias, normal NaN).
    """
    T, F = traj_contact.shape
    D = traj_impulse.shape[-1]
    on = traj_contact.astype(bool)
    force = traj_impulse / dt_true
    scale = fx.find(effects, "force_scale")
    if scale is not None:
        force = force * scale["gain"]
    # draw every noise value whatever the contact pattern: same seed, same draws
    f_noise = rng.normal(0.0, 1.0, size=(T, F, D)) * noise_force
    force = np.where(on[..., None], force + f_noise, 0.0)
    if D == 2:
        n_noise = rng.normal(0.0, 1.0, size=(T, F)) * noise_normal
        normal = np.where(on[..., None], _rotate(traj_normal, n_noise), np.nan)
    else:
        n_noise = rng.normal(0.0, 1.0, size=(T, F, 3)) * noise_normal
        normal = np.where(on[..., None], _tilt(traj_normal, n_noise), np.nan)
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    bias = fx.find(effects, "force_bias")
    b = np.zeros(D) if bias is None else np.array([bias[k] for k in ("fx", "fy", "fz")[:D]])
    force = force + b
    contact = on.astype(np.uint8)
    lat = fx.find(effects, "latency")
    if lat is not None:
        k = min(int(lat["samples"]), T)
        contact = np.concatenate([np.zeros((k, F), np.uint8), contact[:T - k]])
        force = np.concatenate([np.broadcast_to(b, (k, F, D)), force[:T - k]])
        normal = np.concatenate([np.full((k, F, D), np.nan), normal[:T - k]])
    return contact, force, normal


def _time_scale(effects) -> float:
    ts = fx.find(effects, "time_scale")
    return 1.0 if ts is None else float(ts["scale"])


def _make_run(traj: _Trajectory, state0: WorldState, opts: SimOptions, rng_noise, prior_shape=None) -> Run:
    effects = state0.effects
    obj = state0.obj
    scale = _time_scale(effects)
    T, F, _ = traj.p_finger__world.shape
    dt = float(opts.dt)
    p_meas = traj.p_finger__world + rng_noise.normal(0.0, 1.0, size=(T, F, 2)) * opts.noise_position
    contact, force, normal = sensor_streams(traj.contact, traj.impulse__world, traj.normal__world, dt,
                                            effects, opts.noise_force, opts.noise_normal, rng_noise)
    run = Run(
        dim=2, dt=scale * dt, time=scale * traj.t_true, gravity=np.array([0.0, -GRAVITY]), source="sim",
        finger_position=p_meas, finger_radius=np.asarray(state0.finger_radius, float).copy(),
        contact=contact, force=force if opts.force_stream else None, normal=normal,
        actions=Actions(segments=traj.segments, params=traj.params, kind=POKE_KIND, names=list(POKE_NAMES)),
        ground_height=0.0, ground_normal=np.array([0.0, 1.0]),
        prior={"size_bound": SIZE_BOUND, "shape": prior_shape or obj.shape},
        truth=Truth(pose=traj.pose, vertices=obj.vertices.copy(), mass=obj.mass, inertia=obj.inertia,
                    friction_ground=obj.friction_ground, friction_finger=obj.friction_finger,
                    effects=json.loads(fx.effects_to_json(effects))),
        extra_attrs={"noise_force": float(opts.noise_force), "noise_position": float(opts.noise_position),
                     "noise_normal": float(opts.noise_normal)},
    )
    if opts.observe_pose is not None:
        sigma = max(float(opts.observe_pose), 1e-9)
        sig = np.array([sigma, sigma, sigma / POSE_ANGLE_LEVER])
        run.pose_obs = traj.pose + rng_noise.normal(0.0, 1.0, size=(T, 3)) * sig * (opts.observe_pose > 0)
        run.sigma_position, run.sigma_angle = float(sig[0]), float(sig[2])
    return run


def simulate_pokes(state, actions, opts: SimOptions = None,
                   names=POKE_NAMES, noise_key: int = 0, settle_first: bool = False) -> Run:
    """Simulate the given pokes from ``state`` and return the recorded Run (with truth).

    state : WorldState, e.g. from :func:`initial_state`, :func:`state_from_run`, or built
        from an estimate (``WorldState(SimObject(...), pose, zeros(3), p_finger, radius)``);
        or a SimObject, placed by :func:`state_at_rest` with ``opts.fingers`` fingers;
    actions : (A, n) poke parameter vectors whose columns are ``names`` (default
        POKE_NAMES); targets are used as given;
    opts : noise levels, dt, streams (SimOptions; its object/seed/pokes/effects are not
        used: the object and effects are the state's); noise draws from stream
        (opts.seed, noise_key); settle_first : the state is a toss (:func:`toss_state`):
        record until the object has come to rest before the first poke (with no poke:
        until it has come to rest, plus SETTLE_TIME).
    Sample 0 is ``state`` itself; poke i covers /actions/segments[i].
    """
    opts = (opts or SimOptions()).validate()
    if isinstance(state, SimObject):
        state = state_at_rest(state, fingers=opts.fingers, finger_radius=opts.finger_radius)
    acts = np.asarray(actions, float)
    if acts.size == 0:
        acts = acts.reshape(0, len(names))
    if acts.ndim == 1:
        acts = acts[None, :]
    sources = [Poke.from_vector(a, state.n_fingers, names).to_vector() for a in acts]
    traj = _simulate(state, sources, opts, _rng(opts.seed, _STREAM_POKES, noise_key), settle_first=settle_first)
    return _make_run(traj, state, opts, _rng(opts.seed, _STREAM_NOISE, noise_key))


# ---------------------------------------------------------------------------------
# continuing a run


def state_from_run(run: Run) -> WorldState:
    """The world at the last sample of a simulated run (from its /truth).

    The velocity is the finite difference of the last two truth poses; the fingers are
    at their last measured positions; a soft ground starts at the object's static
    sinkage.  A run without /truth cannot be continued (TacestError).
    """
    where = run.filename or "run"
    if run.dim != 2:
        raise TacestError(f"{where}: is a {run.dim}-D run; continue it with --dim {run.dim}")
    if run.truth is None:
        raise TacestError(f"{where}: has no /truth, so the simulation cannot continue it "
                          "(record it without --no-truth)")
    if run.finger_position is None:
        raise TacestError(f"{where}: has no /robot group, so there are no fingers to continue with")
    tr = run.truth
    try:
        effects = fx.effects_from_json(tr.effects)
    except TacestError as exc:
        raise TacestError(f"{where}: /truth attrs effects: {exc}") from None
    for name in ("mass", "inertia", "friction_ground", "friction_finger"):
        v = getattr(tr, name)
        if v is None or not np.isfinite(v) or v <= 0:
            raise TacestError(f"{where}: /truth attrs {name} is missing or not > 0")
    vertices = np.asarray(tr.vertices, float)
    if signed_area(vertices) < 0:  # clockwise: make it counter-clockwise
        vertices = vertices[::-1].copy()
    obj = SimObject(vertices=vertices, mass=float(tr.mass), inertia=float(tr.inertia),
                    friction_ground=float(tr.friction_ground), friction_finger=float(tr.friction_finger),
                    shape=str(run.prior.get("shape", "polygon")))
    scale = _time_scale(effects)
    dt_true = run.dt / scale
    pose = np.asarray(tr.pose[-1], float)
    velocity = (pose - np.asarray(tr.pose[-2], float)) / dt_true
    return WorldState(obj=obj, pose=pose, velocity=velocity,
                      p_finger__world=np.asarray(run.finger_position[-1], float).copy(),
                      finger_radius=np.asarray(run.finger_radius, float).copy(), effects=effects,
                      time=float(run.time[-1]) / scale, ground_state=_static_ground(obj, effects))


def append_run(old: Run, new: Run, names=POKE_NAMES) -> Run:
    """``old`` followed by ``new``, a continuation whose sample 0 is ``old``'s last sample
    (that duplicate is dropped; actions are re-indexed).  names : the poke parameter
    names both runs' actions must have (tacest.sim3d passes its 3-D names)."""
    off = old.n_samples - 1

    def cat(a, b):
        if a is None or b is None:
            return None
        return np.concatenate([np.asarray(a), np.asarray(b)[1:]])

    segs, params = [], []
    names, kind = list(names), POKE_KIND
    if old.actions is not None and len(old.actions.segments):
        if [str(n) for n in old.actions.names] not in ([], names) or old.actions.kind != POKE_KIND:
            raise TacestError(f"{old.filename or 'run'}: its actions are not pokes ({old.actions.kind}: "
                              f"{', '.join(map(str, old.actions.names))}); cannot append pokes")
        segs.append(np.asarray(old.actions.segments))
        params.append(np.asarray(old.actions.params))
    if new.actions is not None:
        segs.append(np.asarray(new.actions.segments) + off)
        params.append(np.asarray(new.actions.params))
    truth = None
    if old.truth is not None and new.truth is not None:
        truth = Truth(pose=cat(old.truth.pose, new.truth.pose), vertices=old.truth.vertices, mass=old.truth.mass,
                      inertia=old.truth.inertia, friction_ground=old.truth.friction_ground,
                      friction_finger=old.truth.friction_finger, effects=old.truth.effects)
    missing = None
    if old.missing is not None:
        missing = np.concatenate([old.missing, np.zeros(new.n_samples - 1, np.uint8)])
    return old.replace(
        time=cat(old.time, new.time), finger_position=cat(old.finger_position, new.finger_position),
        contact=cat(old.contact, new.contact), force=cat(old.force, new.force), normal=cat(old.normal, new.normal),
        pose_obs=cat(old.pose_obs, new.pose_obs),
        actions=Actions(segments=np.concatenate(segs).astype(np.int64) if segs else np.zeros((0, 2), np.int64),
                        params=np.concatenate(params) if params else np.zeros((0, len(names))), kind=kind,
                        names=names),
        truth=truth, missing=missing, filename=None)


# ---------------------------------------------------------------------------------
# the recorder


def simulate_aimed_pokes(aim: Callable, n: int, opts: SimOptions, state: WorldState = None,
                         run: Run = None) -> Run:
    """Simulate ``n`` pokes one after another, each aimed at the object as it is when
    that poke starts, and return the whole run (``append_run`` of the parts).

    aim(i, state) -> poke vector (POKE_NAMES) of poke i, from the WorldState it starts
    from; state : the WorldState of the first poke when ``run`` is None; run : a Run
    (with /truth) to continue from its last truth state.  Poke i draws its noise from
    key i + 1 (simulate_pokes' noise_key).
    """
    for i in range(n):
        st = state if run is None else state_from_run(run)
        part = simulate_pokes(st, np.asarray(aim(i, st), float)[None], opts, noise_key=i + 1)
        run = part if run is None else append_run(run, part)
    return run


def _plan_pokes(plan_path):
    from tacest.io.plan import read_plan

    plan = read_plan(plan_path)
    if plan.kind != POKE_KIND:
        raise TacestError(f"{plan_path}: plan action kind is {plan.kind!r}; the simulator executes 'poke'")
    return plan


#: root attr of a simulated run: JSON list, one entry per recording that made it
#: (docs/simulation.md, "Reproducing a simulated run")
SIM_OPTIONS_ATTR = "sim_options"


def _effect_text(effect) -> str:
    """An effect as the ``--effect`` text that gives it (strings are kept as given)."""
    if isinstance(effect, str):
        return effect

    def value(v):
        return ";".join(repr(float(x)) for x in v) if isinstance(v, list) else repr(v)

    params = ",".join(f"{k}={value(v)}" for k, v in effect.params.items())
    return effect.name + (f":{params}" if params else "")


def sim_options_entry(opts: SimOptions, plan_path=None, start_sample: int = 0) -> dict:
    """One recording's entry of the run attr ``sim_options``: ``options`` (every
    SimOptions field, effects as ``--effect`` texts: ``tacest.dims.record_sim(SimOptions(**options))``
    records the same run again), and for a planned poke ``plan`` (file and SHA-256),
    for a continuation ``start_sample`` (the sample of the run it starts from)."""
    import dataclasses

    from tacest.io.h5util import sha256_file

    options = {f.name: getattr(opts, f.name) for f in dataclasses.fields(SimOptions)}
    options["effects"] = [_effect_text(e) for e in opts.effects]
    entry = {"options": options}
    if plan_path is not None:
        entry["plan"] = {"file": str(plan_path), "sha256": sha256_file(plan_path)}
    if start_sample:
        entry["start_sample"] = int(start_sample)
    return entry


def note_sim_options(run: Run, opts: SimOptions, plan_path=None, append_to=None) -> Run:
    """Note in the root attr ``sim_options`` of a just recorded ``run`` how it was made
    (:func:`sim_options_entry`; a continuation of ``append_to`` adds its entry to the
    continued run's list).  Used by the 2-D and the 3-D recorder; returns ``run``."""
    entries = []
    if append_to is not None and SIM_OPTIONS_ATTR in run.extra_attrs:
        from tacest.io.h5util import attr_str

        try:
            entries = list(json.loads(attr_str(run.extra_attrs[SIM_OPTIONS_ATTR])))
        except (json.JSONDecodeError, TypeError):
            entries = []
    start = 0
    if append_to is not None:
        from tacest.io.run import read_run

        start = read_run(append_to).n_samples - 1
    entries.append(sim_options_entry(opts, plan_path, start))
    run.extra_attrs[SIM_OPTIONS_ATTR] = json.dumps(entries, sort_keys=True)
    return run


def record_sim(opts: SimOptions, plan_path=None, append_to=None) -> Run:
    """Record a simulated 2-D run (:func:`_record`) and note how in its root attr
    ``sim_options`` (:func:`note_sim_options`)."""
    run = _record(opts, plan_path=plan_path, append_to=append_to)
    return note_sim_options(run, opts, plan_path, append_to)


def _record(opts: SimOptions, plan_path=None, append_to=None) -> Run:
    """Record a simulated run.

    Without ``plan_path``: ``opts.pokes`` random pokes.  With ``plan_path``: the plan's
    ``/chosen/params`` as one poke (its target as given, i.e. from the estimate).
    With ``append_to`` (an existing run file with /truth): continue that run's world
    (object, effects, last truth state, fingers, dt, streams) and return the whole run,
    old samples first; otherwise a new object from ``opts``.
    Progress lines go to the module's logger.
    The 2-D world; tacest.dims.record_sim records in the world of ``opts.dim``.
    """
    opts.validate()
    if int(opts.dim) != 2:
        raise TacestError(f"the 2-D recorder got dim {opts.dim}; tacest.dims.record_sim records in any dimension")
    plan = _plan_pokes(plan_path) if plan_path is not None else None
    if append_to is None:
        state = initial_state(opts)
        if opts.toss:
            state = toss_state(state, _rng(opts.seed, _STREAM_TOSS))
        if plan is not None:
            sources = [Poke.from_vector(plan.chosen, state.n_fingers, plan.names).to_vector()]
            log.info(f"executing the planned poke of {plan_path} ({plan.method}, {plan.score})")
        else:
            sources = [None] * int(opts.pokes)
        traj = _simulate(state, sources, opts, _rng(opts.seed, _STREAM_POKES), settle_first=opts.toss)
        return _make_run(traj, state, opts, _rng(opts.seed, _STREAM_NOISE))

    from tacest.io.run import read_run

    if opts.toss:
        raise TacestError(f"--toss starts a new recording; it cannot continue {append_to}")
    old = read_run(append_to)
    state = state_from_run(old)
    # the continuation keeps the old run's clock and streams
    cont = SimOptions(**{**opts.__dict__})
    cont.dt = old.dt / _time_scale(state.effects)
    cont.fingers = state.n_fingers
    cont.force_stream = old.has_force
    cont.observe_pose = old.sigma_position if old.has_pose_obs else None
    for name in ("noise_force", "noise_position", "noise_normal"):
        if name in old.extra_attrs:
            setattr(cont, name, float(np.asarray(old.extra_attrs[name])))
    if plan is not None:
        sources = [Poke.from_vector(plan.chosen, state.n_fingers, plan.names).to_vector()]
        log.info(f"executing the planned poke of {plan_path} after sample {old.n_samples - 1} of {append_to}")
    else:
        sources = [None] * int(opts.pokes)
    key = old.n_samples  # fresh noise and poke draws for every continuation
    traj = _simulate(state, sources, cont, _rng(opts.seed, _STREAM_POKES, key), lead_idle=True)
    new = _make_run(traj, state, cont, _rng(opts.seed, _STREAM_NOISE, key), prior_shape=old.prior.get("shape"))
    return append_run(old, new)

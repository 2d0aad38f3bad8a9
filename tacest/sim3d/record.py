"""Simulated 3-D recordings (``tacest record --source sim --dim 3``): pokes in the MuJoCo
world and run files per SPEC (dim = 3).

Public API (the 3-D counterparts of tacest.sim.record; options are its SimOptions)::

    WorldState3                                   object, its state, fingers, effects
    initial_state(opts) -> WorldState3 a new object at rest on the ground
    state_at_rest(obj, xy=(0, 0), quat=None, fingers=1, finger_radius=0.01, effects=()) -> WorldState3
    toss_state(state, rng, xy=None) -> WorldState3  the object released in the air (a toss)
    simulate_pokes(state, actions, opts=None, names=None, settle_first=False, random_pokes=0) -> Run
    record_sim(opts, plan_path=None, append_to=None) -> Run
    state_from_run(run) -> WorldState3            continue from a run's last truth state

Everything per sample is as in 2-D (docs/simulation.md): sample k covers (t[k-1], t[k]];
contact = touched in any substep; force = summed substep contact impulses of the finger
ON the object / dt (world frame, N); normal = impulse-weighted mean contact normal,
unit, out of the object into the finger; then the shared sensor model
(tacest.sim.record.sensor_streams: gain, noise, bias, latency) and the clock
(time_scale).  The random streams of one seed (object, effects, pokes, noise) are the
2-D ones.
"""

from __future__ import annotations

import logging

import json
import math
from dataclasses import dataclass, field


import numpy as np

from tacest.errors import TacestError
from tacest.geometry.transforms import (quat_conjugate, quat_from_axis_angle, quat_multiply, quat_normalize,
                                        quat_to_matrix)
from tacest.io.run import Actions, Run, Truth
from tacest.sim import effects as fx
from tacest.sim.record import (EMPTY_TIME, PARK_HEIGHT, PARK_SPACING, POSE_ANGLE_LEVER, PRE_ROLL, REST_OMEGA,
                               REST_SPEED, REST_WAIT, SETTLE_TIME, SIZE_BOUND, TOSS_DROP, TOSS_LIFT, TOSS_SPEED,
                               TOSS_SPIN, TOSS_WAIT, SimOptions, _rng, _STREAM_NOISE, _STREAM_OBJECT,
                               _STREAM_POKES, _STREAM_TOSS, _time_scale, append_run, note_sim_options,
                               sensor_streams)
from tacest.sim3d.objects import (SimObject3, apply_com_offset, inradius, make_shape, resting_pose, rest_orientation,
                                  uniform_object)
from tacest.sim.pokes import style_of_poke
from tacest.sim3d.pokes import POKE3_NAMES, POKE_KIND, Poke3, poke_path, pokes_from_vector, random_poke
from tacest.sim3d.world import GRAVITY, MAX_FINGER_FORCE, World3

log = logging.getLogger(__name__)


@dataclass
class WorldState3:
    """Everything needed to continue a 3-D simulation.

    obj : SimObject3; pose : (7,) [x, y, z m, qw, qx, qy, qz] of the COM; velocity : (6,)
    [v m/s, ω rad/s], world frame; p_finger__world : (F, 3) m; finger_radius : (F,) m;
    effects : list of resolved Effect (all of them, sensor and clock ones included);
    time : s, true time of this state; ground_state : (2,) [z m, vz m/s] of the
    soft_contact plate.
    """

    obj: SimObject3
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

    def world(self, max_finger_force=MAX_FINGER_FORCE, timestep=5e-4) -> World3:
        """A MuJoCo World3 in this state."""
        return World3(self.obj, self.pose, self.velocity, self.p_finger__world, self.finger_radius, self.effects,
                      ground_state=self.ground_state, max_finger_force=max_finger_force, timestep=timestep)

    @classmethod
    def of(cls, world: World3, effects, time) -> "WorldState3":
        return cls(obj=world.obj, pose=world.pose, velocity=world.velocity, p_finger__world=world.p_finger__world,
                   finger_radius=world.finger_radius.copy(), effects=list(effects), time=float(time),
                   ground_state=world.ground_state)


def _substep(opts: SimOptions) -> float:
    return float(opts.dt) / opts.n_substeps


# ---------------------------------------------------------------------------------
# a new object


def effect_context(obj: SimObject3) -> fx.EffectContext:
    """What the effects' random draws depend on, for a 3-D object (inertia: the mean
    principal moment about the COM, kg·m²)."""
    return fx.EffectContext(mass=obj.mass, inertia=float(np.trace(obj.inertia)) / 3.0,
                            inradius=inradius(obj.vertices), n_faces=obj.n_faces,
                            friction_ground=obj.friction_ground, dim=3)


def initial_state(opts: SimOptions) -> WorldState3:
    """A new object (per ``opts.object_spec`` and ``opts.seed``) at rest on the ground,
    with its effects resolved and the fingers parked above it.

    Draw order in the object stream: shape, mass, frictions, rest face and yaw (random
    polytopes only).  Effects draw from their own streams; ``com_offset`` moves the COM
    before the rest face is chosen.  The world settles for PRE_ROLL s (unrecorded) and
    the velocity is then set to zero, so sample 0 is at rest.
    """
    opts.validate()
    rng = _rng(opts.seed, _STREAM_OBJECT)
    vertices, kind, random_rest = make_shape(opts.object_spec, rng)
    obj = uniform_object(vertices, kind, rng)
    effects = fx.resolve_effects(opts.effects, opts.seed, effect_context(obj))
    com = fx.find(effects, "com_offset")
    if com is not None:
        obj = apply_com_offset(obj, [com["dx"], com["dy"], com["dz"]])
    quat = rest_orientation(obj.vertices, rng if random_rest else None)
    state = state_at_rest(obj, quat=quat, fingers=int(opts.fingers), finger_radius=opts.finger_radius,
                          effects=effects)
    log.info(f"object: {kind}, settling on the ground")  # no parameters: the truth may be hidden
    h = _substep(opts)
    world = state.world(opts.max_finger_force, h)
    hold = world.p_control__world
    for _ in range(int(round(PRE_ROLL / h))):
        world.step(hold, h)
    world.take_measurement()
    settled = WorldState3.of(world, effects, 0.0)
    settled.velocity = np.zeros(6)
    return settled


def _static_ground(obj, effects) -> np.ndarray:
    """(2,) [z, vz] of the soft_contact plate carrying the object's weight (zeros if rigid)."""
    soft = fx.find(effects, "soft_contact")
    if soft is None:
        return np.zeros(2)
    return np.array([-obj.mass * GRAVITY / soft["stiffness"], 0.0])


def state_at_rest(obj: SimObject3, xy=(0.0, 0.0), quat=None, fingers=1, finger_radius=0.01,
                  effects=()) -> WorldState3:
    """``obj`` resting on the ground with its COM at horizontal ``xy`` (2,) m, fingers parked.

    quat : (4,) body-to-world orientation, or None for the stable resting face nearest
    to the body's own orientation; fingers : number of fingertips, parked PARK_HEIGHT
    above the object's top, spaced PARK_SPACING apart along x; effects : resolved
    Effects (a soft_contact ground starts sunk by the object's weight).  Not settled.
    """
    if quat is None:
        quat = rest_orientation(obj.vertices, None)
    effects = list(effects)
    pose = resting_pose(obj.vertices, quat, xy=xy)
    top = float(np.max((obj.vertices @ quat_to_matrix(pose[3:]).T)[:, 2])) + pose[2]
    park = _park(xy, top, fingers, finger_radius)
    ground = _static_ground(obj, effects)
    pose = pose + np.array([0.0, 0.0, ground[0], 0.0, 0.0, 0.0, 0.0])
    return WorldState3(obj=obj, pose=pose, velocity=np.zeros(6), p_finger__world=park,
                       finger_radius=np.full(int(fingers), float(finger_radius)), effects=effects, ground_state=ground)


def _park(xy, top, fingers, finger_radius) -> np.ndarray:
    """(F, 3) m: ``fingers`` fingertips parked PARK_HEIGHT above height ``top`` (m),
    PARK_SPACING apart along x about horizontal ``xy`` (2,) m."""
    F = int(fingers)
    return np.stack([xy[0] + (np.arange(F) - 0.5 * (F - 1)) * PARK_SPACING, np.full(F, float(xy[1])),
                     np.full(F, top + finger_radius + PARK_HEIGHT)], axis=1)


def toss_state(state: WorldState3, rng: np.random.Generator, xy=None) -> WorldState3:
    """``state``'s object released in the air, as by a robot that lets go of it (the 3-D
    ``--toss``; the ranges are the 2-D ones, tacest.sim.record.TOSS_*): at a uniformly
    random orientation with its lowest vertex TOSS_DROP above the ground, its COM over
    horizontal ``xy`` (2,) m (default: where it is now), moving at TOSS_SPEED in a random
    horizontal direction and TOSS_LIFT upwards, spinning at TOSS_SPIN about a uniformly
    random axis.  Draw order from ``rng``: orientation (4 normals), drop, horizontal
    speed, its heading, lift, spin magnitude, spin axis (3 normals).  The fingers are
    parked above the highest point any vertex can reach in the flight; a soft ground
    starts unloaded."""
    obj = state.obj
    quat = quat_normalize(rng.normal(size=4))  # uniform on SO(3)
    drop = float(rng.uniform(*TOSS_DROP))
    speed = float(rng.uniform(*TOSS_SPEED))
    heading = float(rng.uniform(-math.pi, math.pi))
    lift = float(rng.uniform(*TOSS_LIFT))
    spin = float(rng.uniform(*TOSS_SPIN))
    axis = rng.normal(size=3)
    axis /= max(float(np.linalg.norm(axis)), 1e-12)
    xy = np.asarray(state.pose[:2] if xy is None else xy, float)
    pose = resting_pose(obj.vertices, quat, xy=xy) + np.array([0.0, 0.0, drop, 0.0, 0.0, 0.0, 0.0])
    reach = float(np.max(np.linalg.norm(obj.vertices, axis=1)))  # any vertex, any orientation
    top = float(pose[2]) + lift * lift / (2.0 * GRAVITY) + reach
    radius = np.asarray(state.finger_radius, float)
    velocity = np.r_[speed * math.cos(heading), speed * math.sin(heading), lift, spin * axis]
    return WorldState3(obj=obj, pose=pose, velocity=velocity,
                       p_finger__world=_park(xy, top, len(radius), float(np.max(radius))),
                       finger_radius=radius.copy(), effects=list(state.effects), time=state.time,
                       ground_state=np.zeros(2))


# ---------------------------------------------------------------------------------
# simulating pokes


@dataclass
class _Trajectory:
    """True (noise-free) series of a simulation: T samples, F fingers."""

    t_true: np.ndarray  # (T,) s
    p_finger__world: np.ndarray  # (T, F, 3) m
    contact: np.ndarray  # (T, F) bool
    impulse__world: np.ndarray  # (T, F, 3) N·s on the object
    normal__world: np.ndarray  # (T, F, 3) unit or NaN
    pose: np.ndarray  # (T, 7) COM pose
    segments: np.ndarray  # (A, 2) int
    params: np.ndarray  # (A, 8)
    final: WorldState3
    max_penetration_ground: float  # m
    max_penetration_finger: float  # m


def _at_rest(velocity) -> bool:
    return float(np.linalg.norm(velocity[:3])) < REST_SPEED and float(np.linalg.norm(velocity[3:])) < REST_OMEGA


def _random_action(rng: np.random.Generator, world: World3, n_fingers: int, style: str, k: int) -> list:
    """[Poke3] of one random action of ``style`` moving k distinct fingers (k = 1: the
    random poke of tacest.sim3d.pokes.random_poke, as it always was), each with its own
    random poke of that style."""
    pokes = [random_poke(rng, world.centroid__world(), n_fingers, style, world.vertices__world()) for _ in range(k)]
    if k > 1:
        for pk, f in zip(pokes, rng.choice(n_fingers, k, replace=False)):
            pk.finger = int(f)
    return pokes


def _simulate(state: WorldState3, sources, opts: SimOptions, rng_pokes, lead_idle=False,
              settle_first=False) -> _Trajectory:
    """Run the actions ``sources`` (each a (8,) POKE3_NAMES vector, a (k, 8) array of k
    distinct fingers' pokes moving in one action (tacest.sim3d.pokes), or None for a
    random poke) from ``state``.  Every poke but the first (and the first too with
    ``lead_idle``) starts after one idle sample interval, so segments tile the run.
    With ``settle_first`` (a toss) the fingers first hold still until the object has
    come to rest (at most TOSS_WAIT s; then SETTLE_TIME more when there are no pokes):
    those samples belong to no action."""
    dt = float(opts.dt)
    n_sub = opts.n_substeps
    h = dt / n_sub
    world = state.world(opts.max_finger_force, h)
    F = world.n_fingers
    cols = {k: [] for k in ("p", "c", "j", "n", "q")}
    prev_q = [np.asarray(state.pose, float)[3:]]

    def record(m=None):
        cols["p"].append(world.p_finger__world)
        q = world.pose
        if float(q[3:] @ prev_q[0]) < 0:  # keep the quaternion's sign continuous
            q[3:] = -q[3:]
        prev_q[0] = q[3:]
        cols["q"].append(q)
        if m is None:
            cols["c"].append(np.zeros(F, bool))
            cols["j"].append(np.zeros((F, 3)))
            cols["n"].append(np.full((F, 3), np.nan))
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
            pokes = _random_action(rng_pokes, world, F, style_of_poke(opts.poke_style, rng_pokes, i),
                                   int(opts.fingers_per_action))
        else:
            pokes = [Poke3.from_vector(row, F) for row in np.asarray(src, float).reshape(-1, len(POKE3_NAMES))]
        reach = SIZE_BOUND + float(np.max(world.finger_radius))
        s_touch = [world.touch_distance(pk.target__world, pk.direction__world, world.finger_radius[pk.finger],
                                        s_min=-reach, s_max=reach) for pk in pokes]
        top = float(np.max(world.vertices__world()[:, 2]))
        path, _, _ = poke_path(pokes, world.p_control__world, s_touch, top, world.finger_radius)
        extra = SETTLE_TIME if i == A - 1 else 0.0
        n_samples = int(math.ceil((path.duration + extra) / dt - 1e-9))
        ctl = path.at(h * np.arange(1, n_samples * n_sub + 1))
        for k in range(n_samples):
            for j in range(n_sub):
                world.step(ctl[k * n_sub + j], h)
            record(world.take_measurement())
        # like a robot, wait until the object has stopped (a tipped object may still fall)
        hold_until_rest(REST_WAIT)
        for pk in pokes:  # one row per finger; the rows of one action share its segment
            segments.append((start, len(cols["q"])))
            params.append(pk.to_vector())
    if A == 0:
        hold(int(round((SETTLE_TIME if settle_first else EMPTY_TIME) / dt)))
    T = len(cols["q"])
    t_true = state.time + dt * np.arange(T)
    final = WorldState3.of(world, state.effects, t_true[-1])
    final.pose = cols["q"][-1].copy()
    return _Trajectory(
        t_true=t_true, p_finger__world=np.array(cols["p"]), contact=np.array(cols["c"]),
        impulse__world=np.array(cols["j"]), normal__world=np.array(cols["n"]), pose=np.array(cols["q"]),
        segments=np.array(segments, np.int64).reshape(-1, 2), params=np.array(params, float).reshape(-1, 8),
        final=final, max_penetration_ground=world.max_penetration_ground,
        max_penetration_finger=world.max_penetration_finger)


# ---------------------------------------------------------------------------------
# the run file


def perturb_quaternions(q, sigma_angle, rng) -> np.ndarray:
    """Quaternions (T, 4) each rotated by a random rotation vector N(0, sigma_angle² I)
    (rad, world frame): pose-observation noise."""
    w = rng.normal(0.0, 1.0, size=(len(q), 3)) * sigma_angle
    angle = np.linalg.norm(w, axis=1)
    axis = np.where(angle[:, None] > 0, w / np.maximum(angle, 1e-300)[:, None], np.array([1.0, 0.0, 0.0]))
    return quat_normalize(quat_multiply(quat_from_axis_angle(axis, angle), q))


def _make_run(traj: _Trajectory, state0: WorldState3, opts: SimOptions, rng_noise, prior_shape=None) -> Run:
    effects = state0.effects
    obj = state0.obj
    scale = _time_scale(effects)
    T, F, _ = traj.p_finger__world.shape
    dt = float(opts.dt)
    p_meas = traj.p_finger__world + rng_noise.normal(0.0, 1.0, size=(T, F, 3)) * opts.noise_position
    contact, force, normal = sensor_streams(traj.contact, traj.impulse__world, traj.normal__world, dt,
                                            effects, opts.noise_force, opts.noise_normal, rng_noise)
    run = Run(
        dim=3, dt=scale * dt, time=scale * traj.t_true, gravity=np.array([0.0, 0.0, -GRAVITY]), source="sim",
        finger_position=p_meas, finger_radius=np.asarray(state0.finger_radius, float).copy(),
        contact=contact, force=force if opts.force_stream else None, normal=normal,
        actions=Actions(segments=traj.segments, params=traj.params, kind=POKE_KIND, names=list(POKE3_NAMES)),
        ground_height=0.0, ground_normal=np.array([0.0, 0.0, 1.0]),
        prior={"size_bound": SIZE_BOUND, "shape": prior_shape or obj.shape},
        truth=Truth(pose=traj.pose, vertices=obj.vertices.copy(), mass=obj.mass,
                    inertia=np.array(obj.inertia, float), friction_ground=obj.friction_ground,
                    friction_finger=obj.friction_finger, effects=json.loads(fx.effects_to_json(effects))),
        extra_attrs={"noise_force": float(opts.noise_force), "noise_position": float(opts.noise_position),
                     "noise_normal": float(opts.noise_normal)},
    )
    if opts.observe_pose is not None:
        sigma = max(float(opts.observe_pose), 1e-9)
        on = float(opts.observe_pose > 0)
        obs = traj.pose.copy()
        obs[:, :3] += rng_noise.normal(0.0, 1.0, size=(T, 3)) * sigma * on
        obs[:, 3:] = perturb_quaternions(traj.pose[:, 3:], sigma / POSE_ANGLE_LEVER * on, rng_noise)
        run.pose_obs = obs
        run.sigma_position, run.sigma_angle = sigma, sigma / POSE_ANGLE_LEVER
    return run


def simulate_pokes(state, actions, opts: SimOptions = None,
                   names=None, noise_key: int = 0, settle_first: bool = False, random_pokes: int = 0) -> Run:
    """Simulate the given 3-D pokes from ``state`` and return the recorded Run (with truth).

    state : WorldState3 (e.g. from :func:`initial_state` or :func:`state_from_run`), or
        a SimObject3, placed by :func:`state_at_rest` with ``opts.fingers`` fingers;
    actions : (A, n) action vectors whose columns are ``names`` (default: POKE3_NAMES,
        or for n = 8k the k fingers' pokes of tacest.sim3d.pokes.action_names, moving
        together); targets are used as given;
    opts : noise levels, dt, streams (SimOptions; its object, seed, pokes and effects
        are not used: the object and effects are the state's).
    Sample 0 is ``state`` itself; poke i covers /actions/segments[i].  With
    ``settle_first`` (``state`` from :func:`toss_state`) the flight and landing come
    first, until the object is at rest (and SETTLE_TIME more without actions).
    ``random_pokes``: that many random pokes of ``opts.poke_style`` follow the given
    ones, each drawn (from the pokes stream of ``opts.seed`` and ``noise_key``) where
    the object is when it starts, as ``record`` draws them.
    """
    opts = (opts or SimOptions(dim=3)).validate()
    if isinstance(state, SimObject3):
        state = state_at_rest(state, fingers=opts.fingers, finger_radius=opts.finger_radius)
    acts = np.asarray(actions, float)
    if acts.size == 0:
        acts = acts.reshape(0, len(POKE3_NAMES if names is None else names))
    if acts.ndim == 1:
        acts = acts[None, :]
    sources = [_action_rows(a, state.n_fingers, names) for a in acts] + [None] * int(random_pokes)
    traj = _simulate(state, sources, opts, _rng(opts.seed, _STREAM_POKES, noise_key), settle_first=settle_first)
    return _make_run(traj, state, opts, _rng(opts.seed, _STREAM_NOISE, noise_key))


# ---------------------------------------------------------------------------------
# continuing a run


def angular_velocity(q0, q1, dt) -> np.ndarray:
    """(3,) rad/s, world frame: the constant angular velocity that turns unit quaternion
    q0 into q1 in dt s (q1 = exp(ω dt / 2) ⊗ q0)."""
    d = quat_multiply(np.asarray(q1, float), quat_conjugate(np.asarray(q0, float)))
    if d[0] < 0:
        d = -d
    s = float(np.linalg.norm(d[1:]))
    if s < 1e-15:
        return np.zeros(3)
    return d[1:] / s * (2.0 * math.atan2(s, d[0]) / dt)


def state_from_run(run: Run) -> WorldState3:
    """The world at the last sample of a simulated 3-D run (from its /truth).

    The velocity is the finite difference of the last two truth poses; the fingers are
    at their last measured positions; a soft ground starts at the object's static
    sinkage.  A run without /truth cannot be continued (TacestError).
    """
    where = run.filename or "run"
    if run.dim != 3:
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
    for name in ("mass", "friction_ground", "friction_finger"):
        v = getattr(tr, name)
        if v is None or not np.isfinite(v) or v <= 0:
            raise TacestError(f"{where}: /truth attrs {name} is missing or not > 0")
    inertia = None if tr.inertia is None else np.asarray(tr.inertia, float)
    if inertia is None or inertia.shape != (3, 3) or not np.all(np.isfinite(inertia)) \
            or np.any(np.linalg.eigvalsh(0.5 * (inertia + inertia.T)) <= 0):
        raise TacestError(f"{where}: /truth attrs inertia is missing or not a positive definite (3, 3) matrix")
    obj = SimObject3(vertices=np.asarray(tr.vertices, float), mass=float(tr.mass), inertia=inertia,
                     friction_ground=float(tr.friction_ground), friction_finger=float(tr.friction_finger),
                     shape=str(run.prior.get("shape", "polytope")))
    dt_true = run.dt / _time_scale(effects)
    pose = np.asarray(tr.pose[-1], float)
    prev = np.asarray(tr.pose[-2], float)
    velocity = np.concatenate([(pose[:3] - prev[:3]) / dt_true, angular_velocity(prev[3:], pose[3:], dt_true)])
    return WorldState3(obj=obj, pose=pose, velocity=velocity,
                       p_finger__world=np.asarray(run.finger_position[-1], float).copy(),
                       finger_radius=np.asarray(run.finger_radius, float).copy(), effects=effects,
                       time=float(run.time[-1]) / _time_scale(effects), ground_state=_static_ground(obj, effects))


# ---------------------------------------------------------------------------------
# the recorder


def _action_rows(vec, n_fingers, names) -> np.ndarray:
    """(k, 8) POKE3_NAMES rows of the k fingers' pokes of one action vector ``vec``
    named ``names`` (tacest.sim3d.pokes.pokes_from_vector)."""
    return np.array([pk.to_vector() for pk in pokes_from_vector(vec, n_fingers, names)])


def _plan_sources(plan_path, n_fingers, where=""):
    from tacest.io.plan import read_plan

    plan = read_plan(plan_path)
    if plan.kind != POKE_KIND:
        raise TacestError(f"{plan_path}: plan action kind is {plan.kind!r}; the simulator executes 'poke'")
    try:
        src = _action_rows(plan.chosen, n_fingers, plan.names)
    except TacestError as exc:
        raise TacestError(f"{plan_path}: {exc}") from None
    what = "poke" if len(src) == 1 else f"action of {len(src)} fingers"
    log.info(f"executing the planned {what} of {plan_path} ({plan.method}, {plan.score}){where}")
    return [src]


def record_sim(opts: SimOptions, plan_path=None, append_to=None) -> Run:
    """Record a simulated 3-D run (:func:`_record`) and note how in its root attr
    ``sim_options`` (tacest.sim.record.note_sim_options)."""
    run = _record(opts, plan_path=plan_path, append_to=append_to)
    return note_sim_options(run, opts, plan_path, append_to)


def _record(opts: SimOptions, plan_path=None, append_to=None) -> Run:
    """Record a simulated 3-D run (``opts.dim`` = 3).

    Without ``plan_path``: ``opts.pokes`` random pokes.  With ``plan_path``: the plan's
    ``/chosen/params`` (3-D poke names, POKE3_NAMES, and their suffixed copies for the
    other fingers of an action: tacest.sim3d.pokes.action_names) as one action, its
    targets as given.
    With ``append_to`` (an existing 3-D run file with /truth): continue that run's world
    and return the whole run, old samples first; otherwise a new object from ``opts``.
    Progress lines go to the module's logger.
    """
    opts.validate()
    if append_to is None:
        state = initial_state(opts)
        if opts.toss:
            state = toss_state(state, _rng(opts.seed, _STREAM_TOSS))
        if plan_path is not None:
            sources = _plan_sources(plan_path, state.n_fingers)
        else:
            sources = [None] * int(opts.pokes)
        traj = _simulate(state, sources, opts, _rng(opts.seed, _STREAM_POKES), settle_first=opts.toss)
        log.info(f"deepest contact penetration: ground {1e3 * traj.max_penetration_ground:.3f} mm, "
                 f"finger {1e3 * traj.max_penetration_finger:.3f} mm")
        return _make_run(traj, state, opts, _rng(opts.seed, _STREAM_NOISE))

    from tacest.io.run import read_run

    if opts.toss:
        raise TacestError(f"--toss starts a new recording; it cannot continue {append_to}")
    old = read_run(append_to)
    state = state_from_run(old)
    cont = SimOptions(**{**opts.__dict__})
    cont.dt = old.dt / _time_scale(state.effects)
    cont.fingers = state.n_fingers
    cont.force_stream = old.has_force
    cont.observe_pose = old.sigma_position if old.has_pose_obs else None
    for name in ("noise_force", "noise_position", "noise_normal"):
        if name in old.extra_attrs:
            setattr(cont, name, float(np.asarray(old.extra_attrs[name])))
    if plan_path is not None:
        sources = _plan_sources(plan_path, state.n_fingers,
                                f" after sample {old.n_samples - 1} of {append_to}")
    else:
        sources = [None] * int(opts.pokes)
    key = old.n_samples  # fresh noise and poke draws for every continuation
    traj = _simulate(state, sources, cont, _rng(opts.seed, _STREAM_POKES, key), lead_idle=True)
    new = _make_run(traj, state, cont, _rng(opts.seed, _STREAM_NOISE, key), prior_shape=old.prior.get("shape"))
    return append_run(old, new, names=POKE3_NAMES)

"""The 2-D pymunk world: an object on the ground, compliant circular fingertips, and
the physical effects (restitution, angular_damping, linear_drag, soft_contact,
face_friction) injected where they act.

Frames and units: world frame, x to the right, y up, gravity (0, -9.81) m/s², the
ground is the half plane y <= 0; SI units.  Body frame of the object: origin at its
centre of mass.

Fingers.  Each fingertip is a dynamic circle (mass FINGER_MASS, no rotation, weight
compensated) that a kinematic control body drags through a PivotJoint with a limited
force (max_force) and correction speed (max_bias), as in pymunk's "tank" example: the
finger follows the commanded path in free space but gives way when it pushes into the
ground or pinches the object, like a force-limited robot.  The measured fingertip
position is the finger body's position.  Fingers collide with the object and the
ground, not with each other.

pymunk conventions used (pymunk 7, checked by tests/test_sim.py): ``Body.each_arbiter``
hands each arbiter with this body's shape first, ``Arbiter.normal`` points from the
first shape into the second, and ``Arbiter.total_impulse`` is the impulse of the step on
the first shape.  The world visits each finger's arbiters (finger first) and reports
the object's view: the normal out of the object into the finger, the impulse on the
object (both the arbiter's, negated).  Shape friction and elasticity multiply; the
ground's are 1, the object's are the true ground coefficients, and each finger's
friction is friction_finger / (object's friction) so that object-finger contacts get
exactly friction_finger.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tacest.constants import STANDARD_GRAVITY
from tacest.errors import TacestError
from tacest.interrupt import check_interrupt
from tacest.sim.effects import find
from tacest.geometry.transforms import rot2
from tacest.sim.objects import SimObject

GRAVITY = STANDARD_GRAVITY  # m/s², along -y (the simulated world's)
#: kg, mass of each fingertip body (small next to the 0.1-1 kg objects)
FINGER_MASS = 0.05
#: N, force limit of the finger drive (a small robot arm pushes this hard at most)
MAX_FINGER_FORCE = 30.0
#: m/s, fastest speed at which the drive corrects a tracking error
MAX_FINGER_BIAS = 1.0
#: s, time constant of the drive's position error correction
FINGER_ERROR_TIME = 0.01
#: m, pymunk's allowed penetration (its default of 0.1 suits pixels, not metres)
COLLISION_SLOP = 1e-4
#: s, time constant with which pymunk pushes overlapping shapes apart (its default,
#: 0.16 s, lets a toppled object stay 0.5 mm inside the ground for a while)
COLLISION_ERROR_TIME = 0.02
#: solver iterations per step (pymunk's default of 10 is too soft for stacked contacts)
ITERATIONS = 30
#: m, half width of the ground (far larger than any object's travel)
GROUND_HALF_WIDTH = 10.0
#: s, the longest physics substep (0.5 ms: 20 substeps at the default 100 Hz; the
#: recorder's substep count, tacest.sim.record, and the soft plate's mass keep to it)
MAX_SUBSTEP = 5e-4
#: kg, least mass of the ground plate of the soft_contact effect.  The effect is a
#: massless spring k and damper c under the table top (docs/effects.md); the plate is a
#: numerical device and is kept as light as the explicit spring-damper force allows,
#: or every impact would have to set its mass moving, an inertia the effect does not
#: describe (with a 0.2 kg plate the estimator's massless ground fitted a time constant
#: c/k 1.5-4 times the true one).  The force is stable on the unloaded plate for
#: c·h/m < 2 and sqrt(k/m)·h < 2; the plate's mass is m = max(SOFT_PLATE_MASS, c·h,
#: k·h²/2) with h = MAX_SUBSTEP (c·h/m <= 1: an unloaded plate's velocity
#: is damped out in one substep, never reversed).  Loaded, the contact passes the
#: force's impulse on to the object, so the pair moves as the massless model says
#: whatever the plate's share of the mass.  For the drawn effects (c 20-155 N·s/m) the
#: plate is 0.02-0.08 kg.
SOFT_PLATE_MASS = 0.02


@dataclass
class SampleMeasurement:
    """What the fingers felt over one sample interval (F fingers).

    contact : (F,) bool, touched in any substep;
    impulse__world : (F, 2) N·s, summed impulse of each finger ON the object;
    normal__world : (F, 2) unit outward object normal at the contact (impulse-weighted
        mean over the substeps), NaN where no contact.
    """

    contact: np.ndarray
    impulse__world: np.ndarray
    normal__world: np.ndarray


class World:
    """A pymunk space with one object, the ground and F fingertips.

    Parameters
    ----------
    obj : SimObject
    pose : (3,) [x m, y m, angle rad] of the object's COM, world frame
    velocity : (3,) [vx m/s, vy m/s, omega rad/s]
    p_finger__world : (F, 2) m, fingertip centres (control bodies start there too)
    finger_radius : (F,) m
    effects : list of tacest.sim.effects.Effect (physical ones act here, others are ignored)
    ground_state : (2,) [y m, vy m/s] of the soft_contact ground plate (ignored otherwise)
    max_finger_force : N, drive force limit

    ``plate_mass`` (kg) is the soft_contact plate's mass (at least SOFT_PLATE_MASS, see
    there), None on a rigid ground.
    """

    def __init__(self, obj: SimObject, pose, velocity, p_finger__world, finger_radius, effects=(),
                 ground_state=(0.0, 0.0), max_finger_force=MAX_FINGER_FORCE):
        import pymunk

        self.obj = obj
        self.effects = list(effects)
        self.space = space = pymunk.Space()
        space.gravity = (0.0, -GRAVITY)
        space.collision_slop = COLLISION_SLOP
        space.collision_bias = math.exp(-1.0 / COLLISION_ERROR_TIME)  # error fraction left after 1 s
        space.iterations = ITERATIONS

        # -- effects that live in the world -------------------------------------------
        restitution = find(self.effects, "restitution")
        self._e = 0.0 if restitution is None else float(restitution["e"])
        damping = find(self.effects, "angular_damping")
        self._c_ang = 0.0 if damping is None else float(damping["c"])
        drag = find(self.effects, "linear_drag")
        self._b_lin = 0.0 if drag is None else float(drag["b"])
        faces = find(self.effects, "face_friction")
        self._face_mu = None if faces is None else [float(v) for v in faces["values"]]
        if self._face_mu is not None and len(self._face_mu) != obj.n_faces:
            raise TacestError(f"effect face_friction: {len(self._face_mu)} values for {obj.n_faces} faces")
        self._face_normals__body = obj.face_normals__body
        soft = find(self.effects, "soft_contact")

        # -- ground ---------------------------------------------------------------------
        L = GROUND_HALF_WIDTH
        ground_poly = [(-L, -1.0), (L, -1.0), (L, 0.0), (-L, 0.0)]
        if soft is None:
            self.plate = None
            self.plate_mass = None
            self.ground = pymunk.Poly(space.static_body, ground_poly)
            space.add(self.ground)
        else:
            # a light plate on a spring and damper (applied in step()), kept on the
            # vertical axis by a groove
            self._k_soft = float(soft["stiffness"])
            self._c_soft = float(soft["damping"])
            h = MAX_SUBSTEP
            self.plate_mass = max(SOFT_PLATE_MASS, self._c_soft * h, 0.5 * self._k_soft * h * h)
            self.plate = pymunk.Body(self.plate_mass, float("inf"))
            self.plate.position = (0.0, float(ground_state[0]))
            self.plate.velocity = (0.0, float(ground_state[1]))
            self.ground = pymunk.Poly(self.plate, ground_poly)
            groove = pymunk.GrooveJoint(space.static_body, self.plate, (0.0, -1.0), (0.0, 1.0), (0.0, 0.0))
            space.add(self.plate, self.ground, groove)
        self.ground.friction = 1.0
        self.ground.elasticity = 1.0

        # -- object ---------------------------------------------------------------------
        self.body = pymunk.Body(float(obj.mass), float(obj.inertia))
        self.body.position = (float(pose[0]), float(pose[1]))
        self.body.angle = float(pose[2])
        self.body.velocity = (float(velocity[0]), float(velocity[1]))
        self.body.angular_velocity = float(velocity[2])
        self.shape = pymunk.Poly(self.body, [tuple(map(float, v)) for v in obj.vertices])
        self.shape.friction = float(obj.friction_ground)
        self.shape.elasticity = self._e
        space.add(self.body, self.shape)

        # -- fingers ----------------------------------------------------------------------
        p_finger = np.asarray(p_finger__world, float).reshape(-1, 2)
        radius = np.broadcast_to(np.asarray(finger_radius, float), (len(p_finger),))
        self.finger_radius = radius.copy()
        self.fingers, self.finger_shapes, self.controls = [], [], []
        no_self_collision = pymunk.ShapeFilter(group=1)
        error_bias = math.exp(-1.0 / FINGER_ERROR_TIME)  # pymunk: error fraction left after 1 s
        for f, (p, r) in enumerate(zip(p_finger, radius)):
            body = pymunk.Body(FINGER_MASS, float("inf"))
            body.position = (float(p[0]), float(p[1]))
            shape = pymunk.Circle(body, float(r))
            shape.elasticity = 1.0
            shape.filter = no_self_collision
            control = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
            control.position = body.position
            joint = pymunk.PivotJoint(control, body, (0.0, 0.0), (0.0, 0.0))
            joint.max_force = float(max_finger_force)
            joint.max_bias = MAX_FINGER_BIAS
            joint.error_bias = error_bias
            space.add(body, shape, control, joint)
            self.fingers.append(body)
            self.finger_shapes.append(shape)
            self.controls.append(control)
        self._finger_callbacks = [self._finger_callback(f) for f in range(len(self.fingers))]
        self._set_friction(self._ground_mu())
        self._reset_accumulators()

    # -- state -----------------------------------------------------------------------
    @property
    def n_fingers(self) -> int:
        return len(self.fingers)

    @property
    def pose(self) -> np.ndarray:
        """(3,) [x, y, angle] of the object's COM, world frame (m, m, rad)."""
        p = self.body.position
        return np.array([p.x, p.y, self.body.angle])

    @property
    def velocity(self) -> np.ndarray:
        """(3,) [vx, vy, omega] of the object (m/s, m/s, rad/s)."""
        v = self.body.velocity
        return np.array([v.x, v.y, self.body.angular_velocity])

    @property
    def p_finger__world(self) -> np.ndarray:
        """(F, 2) m, fingertip centres (the finger bodies, not the commands)."""
        return np.array([[b.position.x, b.position.y] for b in self.fingers])

    @property
    def p_control__world(self) -> np.ndarray:
        """(F, 2) m, commanded positions (the kinematic control bodies)."""
        return np.array([[b.position.x, b.position.y] for b in self.controls])

    @property
    def ground_state(self) -> np.ndarray:
        """(2,) [y m, vy m/s] of the soft ground plate (zeros for a rigid ground)."""
        if self.plate is None:
            return np.zeros(2)
        return np.array([self.plate.position.y, self.plate.velocity.y])

    def vertices__world(self) -> np.ndarray:
        """(K, 2) m, object vertices in the world frame."""
        pose = self.pose
        return self.obj.vertices @ rot2(pose[2]).T + pose[:2]

    def centroid__world(self) -> np.ndarray:
        """(2,) m, the shape's area centroid in the world frame."""
        pose = self.pose
        return rot2(pose[2]) @ self.obj.centroid__body + pose[:2]

    def touch_distance(self, target__world, direction__world, radius, reach=1.0):
        """Distance s (m) from ``target`` along unit ``direction`` at which a circle of
        ``radius`` coming from ``target + reach·direction`` first touches the object,
        or None if that line misses it."""
        t = np.asarray(target__world, float)
        start = t + reach * np.asarray(direction__world, float)
        info = self.shape.segment_query(tuple(start), tuple(t), float(radius))
        if info is None or info.shape is None:  # pymunk 7 returns None for a miss
            return None
        return reach * (1.0 - float(info.alpha))

    # -- stepping --------------------------------------------------------------------
    def _ground_mu(self) -> float:
        if self._face_mu is None:
            return float(self.obj.friction_ground)
        # the face that faces the ground most: largest downward component of its normal
        c, s = math.cos(self.body.angle), math.sin(self.body.angle)
        ny = self._face_normals__body[:, 0] * s + self._face_normals__body[:, 1] * c
        return self._face_mu[int(np.argmin(ny))]

    def _set_friction(self, mu_ground):
        self.shape.friction = mu_ground
        for shape in self.finger_shapes:
            shape.friction = float(self.obj.friction_finger) / mu_ground

    def step(self, p_control_next__world, h):
        """Advance one physics substep of ``h`` s, moving each control body in a straight
        line to ``p_control_next__world`` (F, 2) m, and accumulate what the fingers feel."""
        for control, p in zip(self.controls, p_control_next__world):
            q = control.position
            control.velocity = ((p[0] - q.x) / h, (p[1] - q.y) / h)
        for finger in self.fingers:  # weight compensation: the robot holds its finger up
            finger.force = (0.0, FINGER_MASS * GRAVITY)
        body = self.body
        if self._b_lin:
            v = body.velocity
            body.force = (-self._b_lin * v.x, -self._b_lin * v.y)
        if self._c_ang:
            body.torque = -self._c_ang * body.angular_velocity
        if self.plate is not None:  # spring, damper, and the plate's own weight held up
            y, vy = self.plate.position.y, self.plate.velocity.y
            self.plate.force = (0.0, self.plate_mass * GRAVITY - self._k_soft * y - self._c_soft * vy)
        if self._face_mu is not None:
            self._set_friction(self._ground_mu())
        self.space.step(h)
        for control, p in zip(self.controls, p_control_next__world):
            control.position = (float(p[0]), float(p[1]))
        # each finger's arbiters (with the object or the ground), not the object's: the
        # object rests on the ground at nearly every substep, and visiting that arbiter
        # from Python cost as much as the physics step itself
        for callback, finger in zip(self._finger_callbacks, self.fingers):
            finger.each_arbiter(callback)
        # a Ctrl-C noted during the callbacks (the simulators run in
        # tacest.interrupt.deferred_interrupts): raised here, outside cffi
        check_interrupt()

    def _finger_callback(self, f):
        """Arbiter callback of finger f: accumulates what the finger feels of the object."""
        obj = self.shape

        def on_arbiter(arb):
            # arbiter shapes: (finger shape, other shape); normal from the finger into the
            # object, impulse on the finger: both negated (exactly) to the object's view
            # of the module docstring
            if arb.shapes[1] is not obj or not arb.contact_point_set.points:
                return
            j = arb.total_impulse
            n = arb.normal
            jx, jy, nx, ny = -j.x, -j.y, -n.x, -n.y
            self._touch[f] = True
            acc = self._impulse[f]
            acc[0] += jx
            acc[1] += jy
            w = abs(jx * nx + jy * ny)
            nacc = self._normal[f]
            nacc[0] += w * nx
            nacc[1] += w * ny
            self._last_normal[f] = (nx, ny)

        return on_arbiter

    def _reset_accumulators(self):
        F = len(self.fingers)
        self._touch = [False] * F
        self._impulse = [[0.0, 0.0] for _ in range(F)]
        self._normal = [[0.0, 0.0] for _ in range(F)]
        self._last_normal = [None] * F

    def take_measurement(self) -> SampleMeasurement:
        """What the fingers felt since the last call (SampleMeasurement); resets."""
        F = len(self.fingers)
        contact = np.array(self._touch, bool)
        impulse = np.array(self._impulse, float).reshape(F, 2)
        normal = np.full((F, 2), np.nan)
        for f in range(F):
            if not self._touch[f]:
                continue
            n = np.array(self._normal[f])
            norm = np.linalg.norm(n)
            normal[f] = n / norm if norm > 1e-12 else np.array(self._last_normal[f])
        self._reset_accumulators()
        return SampleMeasurement(contact, impulse, normal)

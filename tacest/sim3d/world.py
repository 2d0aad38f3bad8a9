"""The 3-D MuJoCo world: an object on the ground, compliant spherical fingertips, and
the physical effects (restitution, angular_damping, linear_drag, soft_contact,
face_friction) injected where they act.

Frames and units: world frame, z up, gravity (0, 0, -9.81) m/s², the ground is the
plane z = 0; SI units.  The MuJoCo body of the object has its frame at the centre of
mass (explicit ``<inertial pos="0 0 0" fullinertia=...>``), so its free-joint qpos is
the SPEC pose ``[x, y, z, qw, qx, qy, qz]``; its collision geometry is the convex hull
of the body-frame vertices (a mesh geom; MuJoCo shifts the mesh to its own inertial
frame and compensates in the geom's pos/quat, so the hull sits where the vertices say,
tested in tests/test_sim3d.py).

Contacts.  Only explicit ``<pair>`` contacts exist (every geom has contype =
conaffinity = 0): object–ground, object–finger f and finger f–ground; fingers do not
touch each other.  A pair's friction is exactly the coefficient it names (MuJoCo
would otherwise take the larger of two geoms' coefficients): friction_ground,
friction_finger, FINGER_GROUND_FRICTION.  Elliptic friction cones (condim 3: sliding
friction, no torsional or rolling friction) with a high IMPRATIO (hard static friction),
solref (CONTACT_TIMECONST, 1) and solimp CONTACT_SOLIMP: a resting object sinks a few
µm, one pressed onto a corner by a finger with 30 N up to ~0.3 mm (tests/test_sim3d.py
checks < 1 mm).  MuJoCo's timestep is the recorder's substep (0.5 ms at 100 Hz).

Fingers.  Each fingertip is a sphere (mass FINGER_MASS, weight compensated by MuJoCo's
``gravcomp``) on three slide joints (it translates, never rotates).  A drive like a
force-limited position-controlled robot pulls it towards the commanded path: the force
``kp·(p_cmd − p) + kd·(v_cmd − v)`` (DRIVE_STIFFNESS, DRIVE_DAMPING: critically damped,
~3 ms time constant) is clipped to ``max_finger_force`` in norm (30 N, as the 2-D
pivot joint's max_force), so a finger follows its path in free space but gives way when
it is blocked.  The measured fingertip position is the sphere's position.

MuJoCo conventions used (checked by tests/test_sim3d.py): ``contact.frame[:3]`` is the
contact normal pointing from ``geom[0]`` to ``geom[1]`` (MuJoCo may order a pair's geoms
by type, so we look at which one is the object), and ``mj_contactForce`` gives, in the
contact frame, the force that geom[0] exerts on geom[1].
"""

from __future__ import annotations

import math

import numpy as np

from tacest.errors import TacestError
from tacest.geometry.polytope import PolytopeSurface
from tacest.geometry.transforms import quat_normalize, quat_to_matrix
from tacest.sim.effects import find
from tacest.sim.world import FINGER_MASS, GRAVITY, MAX_FINGER_FORCE, SampleMeasurement
from tacest.sim3d.objects import SimObject3

__all__ = ["World3", "SampleMeasurement", "GRAVITY", "MAX_FINGER_FORCE", "FINGER_MASS"]

#: N/m, stiffness of the finger drive (with FINGER_MASS: natural frequency ~50 Hz)
DRIVE_STIFFNESS = 5000.0
#: N·s/m, damping of the finger drive (critical: 2·sqrt(k·m))
DRIVE_DAMPING = 2.0 * math.sqrt(DRIVE_STIFFNESS * FINGER_MASS)
#: s, MuJoCo contact solref time constant (stiff: 4 substeps of 0.5 ms; MuJoCo's default
#: 0.02 s lets a polytope pressed onto a corner by 30 N sink several mm)
CONTACT_TIMECONST = 0.002
#: MuJoCo contact solimp (dmin, dmax, width m): impedance 0.95 at touch rising to 0.995 at
#: 1 mm penetration.  Measured: a resting object sinks 2-5 µm, a polytope pressed onto
#: a corner by the finger at 30 N up to ~0.3 mm, the finger into the object ~0.2 mm
CONTACT_SOLIMP = (0.95, 0.995, 0.001)
#: friction coefficient between a fingertip and the table (the 2-D value for a
#: fingertip of friction 0.5 on a ground of 1 is not meaningful either; nothing is
#: recorded about these contacts)
FINGER_GROUND_FRICTION = 0.5
#: s, contact time constant with restitution: a bouncing contact needs several
#: substeps per oscillation (dampratio < 1 makes the spring stiffer)
RESTITUTION_TIMECONST = 0.01
#: m, half extents of the soft_contact plate (a box: MuJoCo planes cannot move)
PLATE_HALF_SIZE = (2.0, 2.0, 0.05)
#: kg, mass of the soft_contact ground plate (the 3-D estimator does not model the
#: effect, NOT_MODELLED_3D; the 2-D simulator's plate is lighter, tacest.sim.world)
SOFT_PLATE_MASS = 0.2
#: MuJoCo solver settings: Newton solver, enough iterations to converge stacked contacts
#: (it typically needs 1-3)
SOLVER_ITERATIONS = 100
SOLVER_TOLERANCE = 1e-10
#: MuJoCo's ratio of frictional to normal constraint impedance.  At 1 (its default) static
#: friction is soft: a finger pressing at 30° from the normal with mu = 0.9 creeps along
#: the face at ~8 mm/s; at 100 it creeps ~0.25 mm/s and steady sliding still follows
#: Coulomb's law to ~0.5 % (tests/test_sim3d.py)
IMPRATIO = 100


def restitution_dampratio(e: float) -> float:
    """Damping ratio ζ of a linear spring-damper contact whose coefficient of
    restitution is e (0 < e < 1): e = exp(-ζπ/sqrt(1-ζ²)) ⇒ ζ = -ln e / sqrt(π² + ln² e)."""
    if e <= 0:
        return 1.0
    L = math.log(e)
    return -L / math.sqrt(math.pi ** 2 + L * L)


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(values, float).ravel())


class World3:
    """A MuJoCo model and data with one object, the ground and F fingertips.

    Parameters
    ----------
    obj : SimObject3
    pose : (7,) [x, y, z m, qw, qx, qy, qz] of the object's COM, world frame
    velocity : (6,) [vx, vy, vz m/s, wx, wy, wz rad/s], world frame (COM velocity)
    p_finger__world : (F, 3) m, fingertip centres (the commands start there too)
    finger_radius : (F,) m
    effects : list of tacest.sim.effects.Effect (physical ones act here, others are ignored)
    ground_state : (2,) [z m, vz m/s] of the soft_contact plate (ignored otherwise)
    max_finger_force : N, drive force limit (norm)
    timestep : s, MuJoCo timestep (``step`` may change it)
    """

    def __init__(self, obj: SimObject3, pose, velocity, p_finger__world, finger_radius, effects=(),
                 ground_state=(0.0, 0.0), max_finger_force=MAX_FINGER_FORCE, timestep=5e-4):
        import mujoco

        self._mj = mujoco
        self.obj = obj
        self.effects = list(effects)
        self.max_finger_force = float(max_finger_force)
        p_finger = np.asarray(p_finger__world, float).reshape(-1, 3)
        F = len(p_finger)
        self.finger_radius = np.broadcast_to(np.asarray(finger_radius, float), (F,)).copy()

        restitution = find(self.effects, "restitution")
        self._e = 0.0 if restitution is None else float(restitution["e"])
        damping = find(self.effects, "angular_damping")
        drag = find(self.effects, "linear_drag")
        soft = find(self.effects, "soft_contact")
        faces = find(self.effects, "face_friction")
        self._face_mu = None if faces is None else np.array([float(v) for v in faces["values"]])
        if self._face_mu is not None and len(self._face_mu) != obj.n_faces:
            raise TacestError(f"effect face_friction: {len(self._face_mu)} values for {obj.n_faces} faces")
        self._face_normals__body = obj.faces.normals

        xml = self._mjcf(obj, F, soft, timestep)
        try:
            self.model = model = mujoco.MjModel.from_xml_string(xml)
        except ValueError as exc:  # a shape MuJoCo cannot mesh
            raise TacestError(f"MuJoCo could not build the object: {str(exc).splitlines()[0]}") from None
        self.data = data = mujoco.MjData(model)
        name = lambda kind, n: mujoco.mj_name2id(model, kind, n)  # noqa: E731
        obj_type = mujoco.mjtObj
        J, G, B, P = obj_type.mjOBJ_JOINT, obj_type.mjOBJ_GEOM, obj_type.mjOBJ_BODY, obj_type.mjOBJ_PAIR
        self._body = name(B, "object")
        self._geom = name(G, "object")
        self._ground_geom = name(G, "ground")
        jo = name(J, "object")
        self._qo = int(model.jnt_qposadr[jo])
        self._vo = int(model.jnt_dofadr[jo])
        self._finger_geoms = np.array([name(G, f"finger{f}") for f in range(F)])
        self._finger_of_geom = {int(g): f for f, g in enumerate(self._finger_geoms)}
        self._fq = np.array([model.jnt_qposadr[name(J, f"finger{f}_{a}")] for f in range(F) for a in "xyz"])
        self._fv = np.array([model.jnt_dofadr[name(J, f"finger{f}_{a}")] for f in range(F) for a in "xyz"])
        # each finger's x, y, z slide joints are consecutive: (qpos address, dof address) of x
        self._finger_adr = [(int(self._fq[3 * f]), int(self._fv[3 * f])) for f in range(F)]
        self._ground_pair = name(P, "object_ground")
        if soft is not None:
            jp = name(J, "plate")
            self._qp, self._vp = int(model.jnt_qposadr[jp]), int(model.jnt_dofadr[jp])
        else:
            self._qp = None
        # linear_drag and angular_damping as joint damping of the free joint: MuJoCo
        # integrates it implicitly (stable for any coefficient); translational dofs are
        # world-frame COM velocity, rotational ones body-frame angular velocity, and an
        # isotropic damping torque -c·ω is the same in either frame
        if drag is not None:
            model.dof_damping[self._vo:self._vo + 3] = float(drag["b"])
        if damping is not None:
            model.dof_damping[self._vo + 3:self._vo + 6] = float(damping["c"])

        pose = np.asarray(pose, float).reshape(7)
        data.qpos[self._qo:self._qo + 3] = pose[:3]
        data.qpos[self._qo + 3:self._qo + 7] = quat_normalize(pose[3:7])
        self.velocity = velocity
        data.qpos[self._fq] = p_finger.ravel()
        if self._qp is not None:
            data.qpos[self._qp] = float(ground_state[0])
            data.qvel[self._vp] = float(ground_state[1])
        self._p_ctl = p_finger.copy()
        self._h = float(timestep)
        self._qpos, self._qvel, self._qfrc = data.qpos, data.qvel, data.qfrc_applied  # views, fixed memory
        mujoco.mj_forward(model, data)
        self._surface = None
        self.max_penetration_ground = 0.0  # m, deepest object-ground contact seen
        self.max_penetration_finger = 0.0  # m, deepest object-finger contact seen
        self._force6 = np.zeros(6)
        self._reset_accumulators()

    # -- model -----------------------------------------------------------------------
    def _mjcf(self, obj, F, soft, timestep) -> str:
        mu_g, mu_f = float(obj.friction_ground), float(obj.friction_finger)
        solimp = _fmt(CONTACT_SOLIMP)
        if self._e > 0:
            obj_solref = f"{RESTITUTION_TIMECONST!r} {restitution_dampratio(self._e)!r}"
        else:
            obj_solref = f"{CONTACT_TIMECONST!r} 1"
        plain_solref = f"{CONTACT_TIMECONST!r} 1"
        I = np.asarray(obj.inertia, float)
        full = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
        if soft is None:
            ground = '<geom name="ground" type="plane" size="0 0 1" contype="0" conaffinity="0"/>'
        else:
            hx, hy, hz = PLATE_HALF_SIZE
            # a plate on a damped spring: joint stiffness/damping are N/m and N·s/m
            ground = (f'<body name="plate" gravcomp="1">'
                      f'<joint name="plate" type="slide" axis="0 0 1" stiffness="{float(soft["stiffness"])!r}" '
                      f'damping="{float(soft["damping"])!r}"/>'
                      f'<inertial pos="0 0 {-hz}" mass="{SOFT_PLATE_MASS}" diaginertia="1 1 1"/>'
                      f'<geom name="ground" type="box" size="{hx} {hy} {hz}" pos="0 0 {-hz}" '
                      f'contype="0" conaffinity="0"/></body>')
        fingers, pairs = [], []
        pairs.append(f'<pair name="object_ground" geom1="object" geom2="ground" condim="3" '
                     f'friction="{mu_g!r} {mu_g!r} 0 0 0" solref="{obj_solref}" solimp="{solimp}"/>')
        for f in range(F):
            r = float(self.finger_radius[f])
            i_sphere = 0.4 * FINGER_MASS * r * r  # solid sphere; it never rotates anyway
            fingers.append(
                f'<body name="finger{f}" gravcomp="1">'
                f'<inertial pos="0 0 0" mass="{FINGER_MASS}" diaginertia="{i_sphere!r} {i_sphere!r} {i_sphere!r}"/>'
                + "".join(f'<joint name="finger{f}_{a}" type="slide" axis="{ax}"/>'
                          for a, ax in zip("xyz", ("1 0 0", "0 1 0", "0 0 1")))
                + f'<geom name="finger{f}" type="sphere" size="{r!r}" contype="0" conaffinity="0"/></body>')
            pairs.append(f'<pair geom1="object" geom2="finger{f}" condim="3" friction="{mu_f!r} {mu_f!r} 0 0 0" '
                         f'solref="{obj_solref}" solimp="{solimp}"/>')
            pairs.append(f'<pair geom1="finger{f}" geom2="ground" condim="3" '
                         f'friction="{FINGER_GROUND_FRICTION} {FINGER_GROUND_FRICTION} 0 0 0" '
                         f'solref="{plain_solref}" solimp="{solimp}"/>')
        return f"""<mujoco model="tacest">
  <compiler angle="radian" inertiafromgeom="false"/>
  <option timestep="{float(timestep)!r}" gravity="0 0 {-GRAVITY}" cone="elliptic" impratio="{IMPRATIO}"
          integrator="implicitfast"
          solver="Newton" iterations="{SOLVER_ITERATIONS}" tolerance="{SOLVER_TOLERANCE}">
    <flag multiccd="enable"/>
  </option>
  <asset><mesh name="object" vertex="{_fmt(obj.vertices)}"/></asset>
  <worldbody>
    {ground}
    <body name="object">
      <freejoint name="object"/>
      <inertial pos="0 0 0" mass="{float(obj.mass)!r}" fullinertia="{_fmt(full)}"/>
      <geom name="object" type="mesh" mesh="object" contype="0" conaffinity="0"/>
    </body>
    {"".join(fingers)}
  </worldbody>
  <contact>
    {"".join(pairs)}
  </contact>
</mujoco>"""

    # -- state -----------------------------------------------------------------------
    @property
    def n_fingers(self) -> int:
        return len(self._finger_geoms)

    @property
    def pose(self) -> np.ndarray:
        """(7,) [x, y, z, qw, qx, qy, qz] of the object's COM, world frame (unit quaternion)."""
        q = np.array(self.data.qpos[self._qo:self._qo + 7])
        q[3:] /= np.linalg.norm(q[3:])
        return q

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) body-to-world rotation of the object."""
        return quat_to_matrix(self.data.qpos[self._qo + 3:self._qo + 7])

    @property
    def velocity(self) -> np.ndarray:
        """(6,) [v (3) m/s, ω (3) rad/s] of the object's COM, world frame."""
        v = np.array(self.data.qvel[self._vo:self._vo + 6])
        return np.concatenate([v[:3], self.rotation @ v[3:]])

    @velocity.setter
    def velocity(self, value):
        v = np.asarray(value, float).reshape(6)
        self.data.qvel[self._vo:self._vo + 3] = v[:3]
        self.data.qvel[self._vo + 3:self._vo + 6] = self.rotation.T @ v[3:]  # MuJoCo: body frame

    @property
    def p_finger__world(self) -> np.ndarray:
        """(F, 3) m, fingertip centres (the spheres, not the commands)."""
        return np.array(self.data.qpos[self._fq]).reshape(-1, 3)

    @property
    def p_control__world(self) -> np.ndarray:
        """(F, 3) m, commanded positions."""
        return self._p_ctl.copy()

    @property
    def ground_state(self) -> np.ndarray:
        """(2,) [z m, vz m/s] of the soft ground plate (zeros for a rigid ground)."""
        if self._qp is None:
            return np.zeros(2)
        return np.array([self.data.qpos[self._qp], self.data.qvel[self._vp]])

    def vertices__world(self) -> np.ndarray:
        """(K, 3) m, object vertices in the world frame."""
        return self.obj.vertices @ self.rotation.T + self.data.qpos[self._qo:self._qo + 3]

    def centroid__world(self) -> np.ndarray:
        """(3,) m, the shape's volume centroid in the world frame."""
        return self.rotation @ self.obj.centroid__body + self.data.qpos[self._qo:self._qo + 3]

    def mesh_vertices__world(self) -> np.ndarray:
        """(K', 3) m, MuJoCo's collision mesh vertices in the world frame (for checks)."""
        m, d = self.model, self.data
        mesh = int(m.geom_dataid[self._geom])
        a, n = int(m.mesh_vertadr[mesh]), int(m.mesh_vertnum[mesh])
        verts = np.array(m.mesh_vert[a:a + n])
        return verts @ np.array(d.geom_xmat[self._geom]).reshape(3, 3).T + d.geom_xpos[self._geom]

    def touch_distance(self, target__world, direction__world, radius, s_min=-1.0, s_max=1.0):
        """The largest s in [s_min, s_max] (m) at which a sphere of ``radius`` centred at
        ``target + s·direction`` touches the object (distance from the centre to the
        solid <= radius): where a sphere coming from ``target + s_max·direction``
        first touches it.  None if it never does."""
        if self._surface is None:
            self._surface = PolytopeSurface(self.obj.vertices)
        R, x = self.rotation, self.data.qpos[self._qo:self._qo + 3]
        t = R.T @ (np.asarray(target__world, float) - x)  # body frame
        d = R.T @ np.asarray(direction__world, float)
        faces = self.obj.faces

        def dist(s):  # (n,) distance from the centres to the solid (0 inside), m
            p = t[None, :] + np.atleast_1d(s)[:, None] * d[None, :]
            out = np.asarray(self._surface.distance(p), float)
            inside = np.all(p @ faces.normals.T <= faces.offsets[None, :], axis=1)
            return np.where(inside, 0.0, out)

        s = np.linspace(s_min, s_max, 801)  # 801 samples: steps of 2.5 mm over 2 m
        hit = np.flatnonzero(dist(s) <= radius)
        if hit.size == 0:
            return None
        i = int(hit[-1])
        if i == len(s) - 1:
            return float(s[-1])
        lo, hi = float(s[i]), float(s[i + 1])
        for _ in range(40):  # bisection to ~1e-14 m
            mid = 0.5 * (lo + hi)
            if dist(mid)[0] <= radius:
                lo = mid
            else:
                hi = mid
        return lo

    def place_finger(self, f: int, p__world) -> None:
        """Put fingertip ``f`` (and its command) at ``p__world`` (3,) m, at rest: a
        prediction starts a poke at its approach point without the transit there."""
        a, b = self._finger_adr[int(f)]
        self.data.qpos[a:a + 3] = np.asarray(p__world, float).reshape(3)
        self.data.qvel[b:b + 3] = 0.0
        self._p_ctl[int(f)] = np.asarray(p__world, float).reshape(3)
        self._mj.mj_forward(self.model, self.data)

    def snapshot(self):
        """The whole state (MuJoCo data, the commands, the penetration records, the
        ground friction face_friction sets) for :meth:`restore`: a world returned to it
        steps exactly as it did from here."""
        d = self._mj.MjData(self.model)
        self._mj.mj_copyData(d, self.model, self.data)
        return (d, self._p_ctl.copy(), self._h, self.max_penetration_ground, self.max_penetration_finger,
                np.array(self.model.pair_friction))

    def restore(self, snap) -> None:
        """Return to a :meth:`snapshot` of this world (what the fingers felt since is dropped)."""
        d, p_ctl, h, pen_ground, pen_finger, pair_friction = snap
        self._mj.mj_copyData(self.data, self.model, d)  # into the same buffers: the views stay valid
        self.model.pair_friction[:] = pair_friction
        self._p_ctl = p_ctl.copy()
        self.model.opt.timestep = self._h = h
        self.max_penetration_ground, self.max_penetration_finger = pen_ground, pen_finger
        self._reset_accumulators()

    # -- stepping --------------------------------------------------------------------
    def _ground_mu(self) -> float:
        # the face that faces the ground most: the most negative world z of its normal
        nz = self._face_normals__body @ self.rotation[2, :]
        return float(self._face_mu[int(np.argmin(nz))])

    def step(self, p_control_next__world, h):
        """Advance one physics substep of ``h`` s, the commands moving in a straight line
        to ``p_control_next__world`` (F, 3) m, and accumulate what the fingers feel."""
        # plain Python floats: for 1-3 fingers far cheaper than numpy's small-array calls
        m, d = self.model, self.data
        if h != self._h:
            m.opt.timestep = self._h = float(h)
        p_next = np.asarray(p_control_next__world, float).reshape(-1, 3)
        qpos, qvel, qfrc = self._qpos, self._qvel, self._qfrc
        kp, kd, fmax, inv_h = DRIVE_STIFFNESS, DRIVE_DAMPING, self.max_finger_force, 1.0 / h
        for (a, b), pn, pc in zip(self._finger_adr, p_next.tolist(), self._p_ctl.tolist()):
            fx = kp * (pn[0] - qpos[a]) + kd * ((pn[0] - pc[0]) * inv_h - qvel[b])
            fy = kp * (pn[1] - qpos[a + 1]) + kd * ((pn[1] - pc[1]) * inv_h - qvel[b + 1])
            fz = kp * (pn[2] - qpos[a + 2]) + kd * ((pn[2] - pc[2]) * inv_h - qvel[b + 2])
            norm = math.sqrt(fx * fx + fy * fy + fz * fz)
            k = fmax / norm if norm > fmax else 1.0
            qfrc[b], qfrc[b + 1], qfrc[b + 2] = k * fx, k * fy, k * fz
        if self._face_mu is not None:
            m.pair_friction[self._ground_pair, :2] = self._ground_mu()
        self._mj.mj_step(m, d)
        self._p_ctl = p_next.copy()
        if d.ncon:
            self._collect(h)

    def _collect(self, h):
        d = self.data
        n = int(d.ncon)
        con = d.contact
        og, gg = self._geom, self._ground_geom
        dists = con.dist[:n].tolist()
        for i, (g0, g1) in enumerate(con.geom[:n].tolist()):
            if g0 == og:
                other, first = g1, True
            elif g1 == og:
                other, first = g0, False
            else:
                continue
            if other == gg:
                if -dists[i] > self.max_penetration_ground:
                    self.max_penetration_ground = -dists[i]
                continue
            f = self._finger_of_geom.get(other)
            if f is None:
                continue
            if -dists[i] > self.max_penetration_finger:
                self.max_penetration_finger = -dists[i]
            self._touch[f] = True
            self._mj.mj_contactForce(self.model, d, i, self._force6)
            frame = np.array(con.frame[i]).reshape(3, 3)  # rows: normal, tangent 1, tangent 2
            f_on_second = frame.T @ self._force6[:3]  # force of geom[0] on geom[1], world frame
            if first:  # geom[0] is the object: the finger feels f_on_second, the object its opposite
                f_obj, n_out = -f_on_second, frame[0]
            else:  # geom[0] is the finger: it pushes the object with f_on_second
                f_obj, n_out = f_on_second, -frame[0]
            self._impulse[f] += f_obj * h
            self._normal[f] += abs(self._force6[0]) * h * n_out
            self._last_normal[f] = n_out

    def _reset_accumulators(self):
        F = self.n_fingers
        self._touch = np.zeros(F, bool)
        self._impulse = np.zeros((F, 3))
        self._normal = np.zeros((F, 3))
        self._last_normal = np.full((F, 3), np.nan)

    def take_measurement(self) -> SampleMeasurement:
        """What the fingers felt since the last call (SampleMeasurement with (F, 3)
        impulses N·s ON the object and unit normals out of the object); resets."""
        F = self.n_fingers
        normal = np.full((F, 3), np.nan)
        for f in np.flatnonzero(self._touch):
            nrm = np.linalg.norm(self._normal[f])
            normal[f] = self._normal[f] / nrm if nrm > 1e-12 else self._last_normal[f]
        m = SampleMeasurement(self._touch.copy(), self._impulse.copy(), normal)
        self._reset_accumulators()
        return m

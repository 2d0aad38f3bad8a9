"""Expected information of a candidate 3-D poke, and the information of the past data
about the object and where it is now: the 3-D counterpart of tacest.information.expected.

A candidate poke (tacest.sim3d.pokes: finger, approach azimuth and elevation, target,
depth, speed) is simulated on the *estimated* object (its vertices, mass, inertia and
frictions) placed at the estimate's final pose in the MuJoCo world (tacest.sim3d.world),
noiseless (:func:`predict_poke_3d`): the poking finger starts at the approach point,
moves straight in at the poke's speed and holds for HOLD_TIME.  The prediction becomes a
run and is fed to the estimator's own per-sample residuals (tacest.model.stage3d through
the compiled kernels of tacest.estimation.problem3d, the estimate's config, effects and
final homotopy stage), linearized at the predicted states: poses from the simulation,
finger impulses the simulated ones, ground impulses fitted by non-negative least squares
(the estimator's own first step).  Kept columns: θ (the estimator's parameters) and the
pose s where the poke starts, as a body-frame twist (δp_b m, δr_b rad: p + R δp_b,
q ⊗ exp(δr_b / 2)); nuisance: every later pose and every contact impulse.  The
information of that linearization comes from tacest.information.sensitivity (``schur``,
``identity``, ``diffsim`` or ``marginal``).

The past (:meth:`ExpectedInformation3D.past_information`) is linearized the same way at
the estimate's own trajectories and impulses, with the pose at the end of the last run
kept: I_past about (θ, the object's pose now), by the same method, plus the estimator's
prior.  (The estimate file's /information/observed holds θ only: the planner needs the
pose too, and how it is correlated with the shape.)  A body-frame twist is the
coordinate in which the identity approximation is exact for a rigid motion: moving the
pose at one time by (δp_b, δr_b) moves every pose reached from it rigidly by the same
body-frame twist.

Rows of the information, in physical units: the estimate's /information/names (shape
``extent_x``.. or ``radius<k>`` m, ``mass`` kg, the log-Cholesky inertia parameters,
frictions, effect parameters) then :data:`POSE_NAMES` (m, rad).  Without a force stream
the mass row is zero (the estimator holds the mass).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.sparse as sp

from tacest.constants import STANDARD_GRAVITY
from tacest.dynamics.rigid3d import align_quaternion_signs, cholesky_from_inertia
from tacest.errors import TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import Scales, choose_scales, touching
from tacest.estimation.estimator3d import data_matrix_3d, effects_3d, global_vector_3d
from tacest.estimation.kernels import compile_functions
from tacest.estimation.problem3d import Problem3D
from tacest.estimation.rollout3d import shape_parameters
from tacest.estimation.uncertainty import effect_factors, information_names_3d
from tacest.geometry.shapes3d import Shape3D, make_shape_3d
from tacest.geometry.transforms import quat_to_matrix
from tacest.information.expected import HOLD_TIME, PREDICT_SUBSTEPS, PredictedPoke, _Buffered, planning_inputs
from tacest.information.sensitivity import Linearized, impulse_prior, information
from tacest.io.run import Run
from tacest.model.priors import prior_head
from tacest.model.registry import resolve
from tacest.model.stage3d import NP, START_TERMS, STAGE_TERMS, TERMS3D, Layout3D, impulse_variable

#: rows of the pose at the reference sample: a body-frame twist (m, rad)
POSE_NAMES = ("pose_x", "pose_y", "pose_z", "pose_rx", "pose_ry", "pose_rz")
#: measurement terms (what a sensor reports); every other term is the model's physics
MEASUREMENT_TERMS_3D = ("force", "normal", "contact", "pose")
#: s, the estimated object settles on the ground this long before a predicted poke (the
#: estimate's pose is consistent with the ground only to the contact tolerance)
SETTLE_TIME = 0.05


def twist_map(q, L: float) -> np.ndarray:
    """(..., 7, 6) d[p / L, q] / d(δp_b, δr_b) of the body-frame twist at unit quaternions
    q (..., 4): p + R δp_b and q ⊗ exp(δr_b / 2) (so dq = ½ q ⊗ [0, δr_b])."""
    q = np.asarray(q, float)
    w, x, y, z = np.moveaxis(q, -1, 0)
    E = np.zeros(q.shape[:-1] + (7, 6))
    E[..., 0:3, 0:3] = quat_to_matrix(q) / L
    E[..., 3:7, 3:6] = 0.5 * np.stack([np.stack([-x, -y, -z], -1), np.stack([w, -z, y], -1),
                                       np.stack([z, w, -x], -1), np.stack([-y, x, w], -1)], -2)
    return E


@dataclass
class ModelState3:
    """What a 3-D estimate says about the object now (scaled as the estimator scales it).

    shape : Shape3D; effects : modelled effect names; scales : Scales (L m, m0 kg, g);
    theta : (n_theta,) the estimator's scaled parameters; vertices : (K, 3) m body frame;
    mass kg; inertia (3, 3) kg·m²; friction_ground, friction_finger; pose : (7,) at the
    end of the last run; p_finger__world : (F, 3) m there; finger_radius : (F,) m; dt s;
    has_force; up : (3,); ground_height m; gravity m/s² (magnitude); config; worlds :
    the settled MuJoCo worlds of its predictions (:func:`settled_world`; not compared,
    not pickled; a model is not changed after it is made).
    """

    shape: Shape3D
    effects: tuple
    scales: Scales
    theta: np.ndarray
    vertices: np.ndarray
    mass: float
    inertia: np.ndarray
    friction_ground: float
    friction_finger: float
    pose: np.ndarray
    p_finger__world: np.ndarray
    finger_radius: np.ndarray
    dt: float
    has_force: bool = False
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    ground_height: float = 0.0
    gravity: float = STANDARD_GRAVITY
    config: EstimatorConfig = field(default_factory=EstimatorConfig)
    worlds: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __getstate__(self):
        return {**self.__dict__, "worlds": {}}

    @property
    def n_fingers(self) -> int:
        return int(len(self.finger_radius))

    @property
    def centroid__world(self) -> np.ndarray:
        """(3,) m: the estimated shape's volume centroid, placed at the final pose."""
        c_b = self.sim_object().centroid__body
        return quat_to_matrix(self.pose[3:]) @ c_b + self.pose[:3]

    def sim_object(self):
        from tacest.sim3d.objects import SimObject3

        return SimObject3(vertices=np.asarray(self.vertices, float).copy(), mass=self.mass,
                          inertia=np.asarray(self.inertia, float), friction_ground=self.friction_ground,
                          friction_finger=self.friction_finger, shape=self.shape.name)

    @classmethod
    def from_estimate(cls, est, runs: list, config: EstimatorConfig) -> "ModelState3":
        """The object of a 3-D Estimate at the end of its last run; ``runs`` the run files
        it was estimated from (same number, lengths and order).  TacestError otherwise."""
        name = est.filename or "estimate"
        shape, V, run = planning_inputs(est, runs, 3, make_shape_3d)
        p = est.params
        for k in ("mass", "friction_ground", "friction_finger"):
            v = float(np.asarray(p.get(k, float("nan"))))
            if not (math.isfinite(v) and v > 0):
                raise TacestError(f"{name}: /params attrs {k} = {v} is not > 0")
        inertia = np.asarray(p.get("inertia", np.full((3, 3), np.nan)), float).reshape(3, 3)
        if not np.all(np.isfinite(inertia)) or np.linalg.eigvalsh(0.5 * (inertia + inertia.T)).min() <= 0:
            raise TacestError(f"{name}: /params attrs inertia is not a positive definite (3, 3) matrix")
        pose = np.asarray(est.runs[-1].pose[-1], float)
        if not np.all(np.isfinite(pose)) or np.linalg.norm(pose[3:]) == 0:
            raise TacestError(f"{name}: the last pose of the last run is not finite")
        pose = np.concatenate([pose[:3], pose[3:] / np.linalg.norm(pose[3:])])
        sc = choose_scales(runs, config)
        L = float(est.extra_attrs.get("length_scale", sc.L))
        m0 = float(est.extra_attrs.get("mass_scale", sc.m0))
        scales = Scales(L=L, m0=m0, g=sc.g)
        effects = tuple(str(e) for e in est.model) if est.model else effects_3d(shape, config)
        # the information's linearization has a stage of three poses: an effect that
        # looks further back (restitution's impacts) is left out of the planning model
        effects = tuple(e for e in effects if not any(x.history_3d for x in resolve(e, 3)))
        theta = theta_of_estimate(shape, effects, V, p, inertia, scales)
        return cls(shape=shape, effects=effects, scales=scales, theta=theta, vertices=V, mass=float(p["mass"]),
                   inertia=inertia, friction_ground=float(p["friction_ground"]),
                   friction_finger=float(p["friction_finger"]), pose=pose,
                   p_finger__world=np.asarray(run.finger_position[-1], float).copy(),
                   finger_radius=np.asarray(run.finger_radius, float).copy(), dt=float(run.dt),
                   has_force=bool(run.has_force), up=np.asarray(run.up, float), ground_height=float(run.ground_height),
                   gravity=float(np.linalg.norm(run.gravity)), config=config)


def theta_of_estimate(shape: Shape3D, effects: tuple, vertices, params: dict, inertia, scales: Scales) -> np.ndarray:
    """(n_theta,) the estimator's scaled parameters of an estimate's /params (the inverse
    of Estimator3D.physical and the effects' reports)."""
    from tacest.model.stage3d import StageModel3D

    model = StageModel3D(shape, 0, effects)
    L, m0 = scales.L, scales.m0
    mass = float(params["mass"])
    th = np.zeros(model.n_theta)
    # the shape's own frame: the body frame's vertices plus the COM offset (com_offset)
    d = np.array([float(params.get(f"com_offset.d{a}", 0.0)) for a in "xyz"])
    th[: model.n_shape] = shape_parameters(shape, np.asarray(vertices, float) + d) / L
    th[model.theta_index("log_mass")] = math.log(mass / m0)
    ns = model.n_shape
    th[ns + 1: ns + 7] = cholesky_from_inertia(np.asarray(inertia, float) / (mass * L * L))
    th[model.theta_index("friction_ground")] = float(params["friction_ground"])
    th[model.theta_index("friction_finger")] = float(params["friction_finger"])
    a = ns + 9
    j = 0
    for e in model.effect_objects:
        try:
            u = e.scaled(params, scales, model.K, float(params["friction_ground"]), 3)
        except KeyError:  # an estimate without the effect's value: its prior centre
            u = {p.name: p.centre for p in e.parameters(model.K, 3)}
        for p in e.parameters(model.K, 3):
            th[a + j] = u[p.name]
            j += 1
    return th


# ---------------------------------------------------------------------------------
# prediction


def settled_world(model: "ModelState3", h: float, settle_time: float, effects=()):
    """The World3 of the estimated object (with ``effects``) lowered (or raised) onto the
    ground at the model's pose, fingers parked above it, after ``settle_time`` s of
    substeps ``h`` s: built and settled once per model and arguments (kept in
    ``model.worlds``), returned to that settled state on every later call (the same
    state, bit for bit, as building and settling anew)."""
    from tacest.sim.effects import find
    from tacest.sim3d.objects import apply_com_offset
    from tacest.sim3d.world import World3

    key = (float(h), float(settle_time), json.dumps([e.to_json_obj() for e in effects], sort_keys=True))
    if key in model.worlds:
        world, snap = model.worlds[key]
        world.restore(snap)
        return world
    obj = model.sim_object()
    com = find(effects, "com_offset")
    if com is not None:
        obj = apply_com_offset(obj, [com["dx"], com["dy"], com["dz"]])
    pose = np.asarray(model.pose, float).copy()
    Vw = obj.vertices @ quat_to_matrix(pose[3:]).T + pose[:3]
    pose[:3] -= (float(np.min(Vw @ model.up)) - model.ground_height) * model.up
    radius = model.finger_radius
    top = float(np.max(Vw[:, 2])) - float(np.min(Vw[:, 2])) + model.ground_height
    parked = np.asarray(model.p_finger__world, float).copy()
    parked[:, 2] = np.maximum(parked[:, 2], top + radius + 0.02)
    world = World3(obj, pose, np.zeros(6), parked, radius, effects=effects, timestep=h)
    hold = world.p_control__world
    for _ in range(int(round(settle_time / h))):
        world.step(hold, h)
    model.worlds[key] = (world, world.snapshot())
    return world


def predict_poke_3d(model: ModelState3, action, substeps: int = PREDICT_SUBSTEPS, hold_time: float = HOLD_TIME,
                    settle_time: float = SETTLE_TIME, effects=()) -> PredictedPoke:
    """Simulate one 3-D action (an (8k,) vector of k fingers' pokes, names
    tacest.sim3d.pokes.action_names(k): one poke for k = 1) on the estimated object,
    noiseless, in the MuJoCo world (module docstring); effects : resolved
    tacest.sim.effects.Effect of the world besides the estimate (as predict_poke's).  The object starts at rest at
    the model's pose lowered (or raised) onto the ground and settles for
    ``settle_time``; idle fingers are parked above it; each poking finger starts at
    ``target + d·(s_touch + CLEARANCE)`` and approaches ``target + d·(s_touch − depth)``
    at its ``speed``, all starting together; then they hold for ``hold_time`` after the
    longest approach.  Sample 0 is the state at the approach points."""
    from tacest.sim.record import SIZE_BOUND
    from tacest.sim3d.pokes import pokes_from_vector

    F = model.n_fingers
    pokes = pokes_from_vector(action, F)
    radius = model.finger_radius
    h = model.dt / int(substeps)
    world = settled_world(model, h, settle_time, effects)
    reach = SIZE_BOUND + float(np.max(radius))
    lines = []  # (finger, start, end, duration s) per poke
    for pk in pokes:
        start, end = pk.approach_line(world.touch_distance(pk.target__world, pk.direction__world, radius[pk.finger],
                                                           s_min=-reach, s_max=reach))
        world.place_finger(pk.finger, start)
        lines.append((pk.finger, start, end, float(np.linalg.norm(end - start)) / pk.speed))
    world.take_measurement()
    duration = max(ln[3] for ln in lines)
    T = int(math.ceil((duration + hold_time) / model.dt - 1e-9)) + 1
    poses, fps = np.empty((T, 7)), np.empty((T, F, 3))
    contact, imp, nrm = np.zeros((T, F), bool), np.zeros((T, F, 3)), np.full((T, F, 3), np.nan)
    poses[0], fps[0] = world.pose, world.p_finger__world
    ctl = world.p_control__world.copy()
    n_sub = int(substeps)
    for k in range(1, T):
        for j in range(n_sub):
            t = ((k - 1) * n_sub + j + 1) * h
            for f, start, end, dur in lines:
                ctl[f] = start + (end - start) * min(t / dur, 1.0)
            world.step(ctl, h)
        m = world.take_measurement()
        poses[k], fps[k] = world.pose, world.p_finger__world
        contact[k], imp[k], nrm[k] = m.contact, m.impulse__world, m.normal__world
    q = np.vstack([model.pose[3:], poses[:, 3:]])
    poses[:, 3:] = align_quaternion_signs(q)[1:]  # continuous, in the estimate's hemisphere
    return PredictedPoke(pose=poses, p_finger__world=fps, contact=contact, impulse__world=imp,
                         normal__world=nrm, dt=model.dt, action=np.concatenate([pk.to_vector() for pk in pokes]))


def prediction_run_3d(pred: PredictedPoke, model: ModelState3) -> Run:
    """The prediction as a noiseless 3-D Run with the model's streams."""
    T = pred.n_samples
    on = pred.contact.astype(bool)
    return Run(dim=3, dt=pred.dt, time=pred.dt * np.arange(T), gravity=-model.gravity * model.up, source="prediction",
               finger_position=pred.p_finger__world.copy(), finger_radius=model.finger_radius.copy(),
               contact=on.astype(np.uint8), force=(pred.impulse__world / pred.dt) if model.has_force else None,
               normal=np.where(on[..., None], pred.normal__world, np.nan), ground_height=model.ground_height,
               ground_normal=model.up.copy())


# ---------------------------------------------------------------------------------
# the linearized residuals


class ExpectedInformation3D:
    """The 3-D information of predicted pokes and of the past, for one model structure
    (shape, fingers, effects, config, scales): the per-sample residual functions and
    their Jacobians, compiled once (the estimator's own kernels), reused for every
    candidate and mapped per length."""

    def __init__(self, shape_spec: str, n_fingers: int, config: EstimatorConfig, effects: tuple, scales: Scales):
        self.shape = make_shape_3d(shape_spec)
        self.F = int(n_fingers)
        self.config = config
        self.scales = scales
        self.pr = pr = Problem3D(self.shape, Layout3D(lengths=(3,), F=self.F), config, tuple(effects))
        if pr.n_poses != 3:
            raise TacestError(f"the 3-D expected information linearizes stages of three poses; effects "
                              f"{', '.join(effects)} look further back (ModelState3 leaves them out)")
        self.K, self.n_theta = pr.K, pr.n_theta
        jr = Problem3D._jacobian_function(pr.res_fun, 6)
        j0 = Problem3D._jacobian_function(pr.res0_fun, 3)
        kern = compile_functions([pr.res_fun, pr.res0_fun, jr, j0], pr.kernel_tag + "_base",
                                 derivatives=(pr.res_fun.name(), pr.res0_fun.name()))  # the estimator's, cached
        self._funs = {"res": _dense(kern[pr.res_fun.name()]), "jac": _dense(kern[jr.name()]),
                      "res0": _dense(kern[pr.res0_fun.name()]), "jac0": _dense(kern[j0.name()])}
        self._direct = tuple(_dense(f) for f in pr.direct_residual_functions())
        self._mapped = {}
        self.names = information_names_3d(pr) + list(POSE_NAMES)
        self.row_terms = _row_terms(pr.stage_fun, STAGE_TERMS), _row_terms(pr.start_fun, START_TERMS)
        self.w = np.array([getattr(config.weights, t) for t in TERMS3D], float)

    def _call(self, key, N, *args):
        fun = self._funs[key] if isinstance(key, str) else key
        name = fun.name()
        if (name, N) not in self._mapped:
            self._mapped[(name, N)] = _Buffered(fun.map(N, "serial") if N != 1 else fun)
        return self._mapped[(name, N)](*args)

    def g_vector(self, has_pose: bool) -> np.ndarray:
        s3 = self.config.solver3d
        eps, comp_mult, dyn_mult = (s3.homotopy if has_pose else s3.homotopy_no_pose)[-1]
        return global_vector_3d(self.config, self.scales, eps, comp_mult, dyn_mult)

    # -- one stretch of samples ---------------------------------------------------------
    def linearize(self, theta, run: Run, poses, LF, U=None, keep=0, has_force=None) -> Linearized:
        """The Linearized residuals (tacest.information.sensitivity) of ``run``'s samples
        at the poses (T, 7) m, finger impulses LF (3F, T-2) and ground-impulse variables U
        (K, T-2) (None: fitted by non-negative least squares), the pose of sample ``keep``
        kept as a body-frame twist (None: no pose kept, its columns zero)."""
        sc = self.scales
        T = run.n_samples
        M = T - 2
        D = data_matrix_3d(run, self.F, sc)
        g = self.g_vector(run.pose_obs is not None)
        X = np.concatenate([np.asarray(poses, float)[:, :3] / sc.L, np.asarray(poses, float)[:, 3:]], 1).T
        LF = np.asarray(LF, float).reshape(3 * self.F, M)
        th = np.asarray(theta, float)
        if U is None:
            U = self.fit_ground(th, X, LF, D, g)
        pt = _PointArgs(X, U, LF, th, D, g, self.w)
        (J,) = self._call("jac", M, *pt.stage())
        (r_s,) = self._call("res", M, *pt.stage())
        n_r = r_s.shape[0]
        J = J.reshape(n_r, M, -1)
        (r0,) = self._call("res0", 1, *pt.start())
        (J0,) = self._call("jac0", 1, *pt.start())
        return self._assemble(pt, r_s, J, r0.reshape(-1), J0.reshape(len(r0), -1), run, keep)

    def fit_ground(self, th, X, LF, D, g) -> np.ndarray:
        """(K, M) ground-impulse variables minimizing the residuals at the given states,
        per interval, lambda_n >= 0 (the estimator's non-negative least squares)."""
        from scipy.optimize import nnls

        res_d, jac_d = self._direct
        M = X.shape[1] - 2
        args = [X[:, :-2], X[:, 1:-1], X[:, 2:], np.zeros((self.K, M)), LF, np.repeat(th[:, None], M, 1), D[:, 2:],
                np.repeat(g[:, None], M, 1), np.repeat(self.w[:, None], M, 1)]
        (r0,) = self._call(res_d, M, *args)
        (A,) = self._call(jac_d, M, *args)
        K = self.K
        LN = np.zeros((K, M))
        for n in range(M):
            LN[:, n] = nnls(A[:, K * n: K * (n + 1)], -r0[:, n])[0]
        return impulse_variable(LN)

    def _assemble(self, pt, r_s, J, r0, J0, run, keep) -> Linearized:
        """Global Jacobian of a stretch from its per-interval blocks (rows: intervals in
        order, then the start block); kept columns θ and the twist of pose ``keep``."""
        K, F, nt = self.K, self.F, self.n_theta
        n_r, M, _ = J.shape
        T = M + 2
        n_X, n_U = NP * T, K * M
        n_full = n_X + n_U + 3 * F * M
        t = np.arange(2, T)[:, None]
        col = np.concatenate([NP * (t - 2) + np.arange(NP), NP * (t - 1) + np.arange(NP), NP * t + np.arange(NP),
                              n_X + K * (t - 2) + np.arange(K), n_X + n_U + 3 * F * (t - 2) + np.arange(3 * F)], 1)
        n_loc = col.shape[1]
        rows = np.arange(M)[None, :, None] * n_r + np.arange(n_r)[:, None, None]
        Jl = J[:, :, :n_loc]
        mask = Jl != 0
        rr, cc, vv = np.broadcast_to(rows, Jl.shape)[mask], np.broadcast_to(col[None], Jl.shape)[mask], Jl[mask]
        n0 = len(r0)
        i0, j0 = np.nonzero(J0[:, :2 * NP])
        R = n_r * M + n0
        Jfull = sp.csc_matrix((np.concatenate([vv, J0[i0, j0]]), (np.concatenate([rr, n_r * M + i0]),
                                                                    np.concatenate([cc, j0]))), shape=(R, n_full))
        Jth = np.concatenate([np.transpose(J[:, :, n_loc:], (1, 0, 2)).reshape(M * n_r, nt), J0[:, 2 * NP:]], 0)
        E = twist_map(pt.X[3:, :].T, self.scales.L)  # (T, NP, 6)
        free = np.ones(n_full, bool)
        on = touching(run)[2:]  # finger impulses are no variables where the flag is 0 (the estimator's bounds)
        free[n_X + n_U:] = np.repeat(on, 3, axis=1).reshape(-1)
        Ja = np.zeros((R, nt + 6))
        Ja[:, :nt] = Jth
        if keep is not None:
            kc = NP * int(keep) + np.arange(NP)
            Ja[:, nt:] = np.asarray(Jfull[:, kc] @ E[int(keep)])
            free[kc] = False
        S = sp.csr_matrix((E.reshape(-1), (np.repeat(np.arange(NP * T), 6), np.tile(np.arange(6), NP * T))),
                          shape=(n_full, 6))  # the twist maps stacked: rows of the poses, zeros below
        idx = np.nonzero(free)[0]
        terms_stage, terms_start = self.row_terms
        term = np.concatenate([np.tile(terms_stage, M), terms_start])
        sample = np.concatenate([np.repeat(np.arange(2, T), n_r), np.ones(n0, int)])
        measured = np.isin(term, MEASUREMENT_TERMS_3D)
        prior = np.zeros(n_full)
        prior[n_X:] = impulse_prior(np.concatenate([pt.U.T.reshape(-1), pt.LF.T.reshape(-1)]))
        lin = Linearized(Ja=Ja, Jx=Jfull[:, idx], r=np.concatenate([r_s.T.reshape(-1), r0]), measured=measured,
                         driving=~measured, sample=sample, S_identity=sp.csc_matrix(S)[idx], n_theta=nt,
                         x_prior=prior[idx], extra={"term": term, "U": pt.U, "LF": pt.LF})
        lin.residual_at = lambda dx: self._residual_at(pt, idx, n_X, n_U, dx)
        return lin

    def _residual_at(self, pt, idx, n_X, n_U, dx) -> np.ndarray:
        """(R,) residuals at the nuisance variables (poses, ground and finger impulses)
        moved by dx (n_x,); or (R, n) at each column of dx (n_x, n), in one mapped call."""
        dx = np.asarray(dx, float)
        cols = dx.reshape(len(idx), -1)
        n = cols.shape[1]
        full = np.zeros((n_X + n_U + pt.LF.size, n))
        full[idx] = cols
        stage, start = [], []
        for i in range(n):
            X = pt.X + full[:n_X, i].reshape(-1, NP).T
            U = pt.U + full[n_X: n_X + n_U, i].reshape(-1, pt.U.shape[0]).T
            LF = pt.LF + full[n_X + n_U:, i].reshape(-1, pt.LF.shape[0]).T
            q = _PointArgs(X, U, LF, pt.theta, pt.D, pt.g, pt.w)
            stage.append(q.stage())
            start.append(q.start())
        M = pt.X.shape[1] - 2
        (r,) = self._call("res", M * n, *[np.concatenate(a, axis=1) for a in zip(*stage)])
        (r0,) = self._call("res0", n, *[np.stack(a, axis=1) for a in zip(*start)])
        out = np.concatenate([r.reshape(r.shape[0], n, M).transpose(2, 0, 1).reshape(-1, n), r0.reshape(-1, n)])
        return out[:, 0] if dx.ndim == 1 else out

    # -- physical units ---------------------------------------------------------------
    def to_physical(self, I_scaled, model: ModelState3) -> np.ndarray:
        """(θ scaled, twist) information -> physical units (names :attr:`names`)."""
        pr, sc = self.pr, self.scales
        d = np.ones(self.n_theta + 6)
        d[: pr.n_shape] = 1.0 / sc.L
        d[pr.n_shape] = 1.0 / model.mass
        a = self.n_theta - pr.n_eff
        d[a: self.n_theta] = effect_factors(pr, model.theta, sc, a)
        I_phys = np.asarray(I_scaled, float) * np.outer(d, d)
        if not model.has_force:  # the estimator holds the mass without a force stream
            k = pr.n_shape
            I_phys[k, :] = 0.0
            I_phys[:, k] = 0.0
        return 0.5 * (I_phys + I_phys.T)

    def prediction(self, model: ModelState3, pred: PredictedPoke) -> Linearized:
        """The Linearized residuals of a predicted poke (start pose kept)."""
        run = prediction_run_3d(pred, model)
        Lam = self.scales.m0 * model.gravity * pred.dt
        LF = (pred.impulse__world[2:] / Lam).reshape(pred.n_samples - 2, -1).T
        return self.linearize(model.theta, run, pred.pose, LF, keep=0)

    def information(self, model: ModelState3, pred: PredictedPoke, method: str = "schur", seed: int = 0) -> np.ndarray:
        """F (n, n) of a predicted poke, physical units, rows :attr:`names`."""
        return self.to_physical(information(self.prediction(model, pred), method, seed=seed), model)

    def prior_information(self, model: ModelState3, size_bound: float = 0.3) -> np.ndarray:
        """(n, n) the estimator's prior on θ (Gauss–Newton of its prior residuals, physical
        units), and a weak prior on the pose (position 1/size_bound², angle 1/π²)."""
        pr = self.pr
        prior = self.prior_vector(model.theta)
        th = ca.SX.sym("th", self.n_theta)
        Jp = np.array(ca.Function("jp", [th], [ca.jacobian(pr.prior_fun(th, prior), th)])(model.theta))
        I = np.zeros((self.n_theta + 6, self.n_theta + 6))
        I[: self.n_theta, : self.n_theta] = Jp.T @ Jp
        I = self.to_physical(I, model)
        if not model.has_force:  # a held mass keeps its prior's information, as 2-D's prior does
            k = pr.n_shape
            I[k, k] = 1.0 / (model.mass * self.config.prior.mass_log_sigma) ** 2
        I[self.n_theta: self.n_theta + 3, self.n_theta: self.n_theta + 3] += np.eye(3) / size_bound ** 2
        I[self.n_theta + 3:, self.n_theta + 3:] += np.eye(3) / math.pi ** 2
        return I

    def prior_vector(self, theta) -> np.ndarray:
        pr, cfg = self.pr, self.config
        return np.concatenate([prior_head(cfg.prior), pr.effect_priors(cfg, self.scales.L),
                               np.asarray(theta, float)[: pr.n_shape]])

    def past_information(self, est, runs, model: ModelState3, method: str = "schur", seed: int = 0) -> np.ndarray:
        """I_past (n, n): the runs' information about θ and the pose now (the end of the
        last run) by ``method`` at the estimate's trajectories and impulses (ground
        impulses fitted where the estimate has none), plus :meth:`prior_information`."""
        total = np.zeros((self.n_theta + 6, self.n_theta + 6))
        for i, (re_, run) in enumerate(zip(est.runs, runs)):
            T = run.n_samples
            Lam = self.scales.m0 * float(np.linalg.norm(run.gravity)) * run.dt
            LF = np.zeros((3 * self.F, T - 2))
            for f in range(run.n_fingers):
                imp = re_.impulses.get(f"finger_{f}")
                if imp is not None:
                    LF[3 * f: 3 * f + 3] = (np.asarray(imp, float)[2:] / Lam).T
                elif run.force is not None:
                    LF[3 * f: 3 * f + 3] = (np.nan_to_num(run.force[2:, f]) * run.dt / Lam).T
            gn = re_.impulses.get("ground_normal")
            U = None if gn is None else impulse_variable(np.asarray(gn, float)[2:].T / Lam)
            poses = np.asarray(re_.pose, float).copy()
            poses[:, 3:] = align_quaternion_signs(poses[:, 3:] / np.linalg.norm(poses[:, 3:], axis=1, keepdims=True))
            lin = self.linearize(model.theta, run, poses, LF, U=U, keep=T - 1 if i == len(runs) - 1 else None)
            total += information(lin, method, seed=seed)
        return self.to_physical(total, model) + self.prior_information(model)


@dataclass
class _PointArgs:
    """The point of a linearization: X (7, T) scaled poses, U (K, T-2), LF (3F, T-2),
    theta, D (n_d, T), g, w; :meth:`stage` / :meth:`start` the mapped functions' inputs."""

    X: np.ndarray
    U: np.ndarray
    LF: np.ndarray
    theta: np.ndarray
    D: np.ndarray
    g: np.ndarray
    w: np.ndarray

    def stage(self):
        M = self.X.shape[1] - 2
        rep = lambda v: np.repeat(np.asarray(v, float)[:, None], M, 1)  # noqa: E731
        return [self.X[:, :-2], self.X[:, 1:-1], self.X[:, 2:], self.U, self.LF, rep(self.theta), self.D[:, 2:],
                rep(self.g), rep(self.w)]

    def start(self):
        return [self.X[:, 0], self.X[:, 1], self.theta, self.D[:, 0], self.D[:, 1], self.g, self.w]


def _dense(fun):
    """``fun`` with dense outputs (for :class:`_Buffered`)."""
    ins = fun.mx_in()
    return ca.Function(f"dense_{fun.name()}", ins, [ca.densify(o) for o in fun.call(ins)])


def _row_terms(fun, terms) -> np.ndarray:
    """(n_rows,) the term of each row of the stacked residual of ``fun``'s ``terms``
    (then its quaternion-norm rows), as Problem3D._residual_function stacks them."""
    out = []
    for t in (*terms, "quat_norm"):
        out += [t] * int(np.prod(fun.size_out(t)))
    return np.array(out, dtype=object)


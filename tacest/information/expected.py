"""Expected (Fisher) information of a candidate poke, predicted from an estimate.

A candidate action is simulated from the current estimate with tacest's own model: the
estimated object (vertices, mass, inertia, frictions) placed at the estimated final pose
of the last run in the pymunk world (tacest.sim.world), noiseless
(:func:`predict_poke`).  The prediction is turned into a run of T samples and the
estimator's own per-sample residuals (tacest.model.stage2d: the same stage and start
functions, noise levels, weights and homotopy end point as the estimate) are
linearized there.  With r the stacked whitened residuals and J = [J_θ, J_s, J_x] their
Jacobian with respect to the parameters θ, the start pose s of the poke (the estimate's
final pose: the poke starts where the past data left the object) and the nuisance
variables x (every later pose, velocity and contact impulse), the expected information is
the Schur complement

    F = J_aᵀJ_a − J_aᵀJ_x (J_xᵀJ_x + δI)⁻¹ J_xᵀJ_a,     a = (θ, s),

exactly as :mod:`tacest.estimation.uncertainty` computes I_obs from the recorded data, so
F and I_obs are comparable entry by entry (same names, same physical units).  For
Gaussian noise on the whitened residuals JᵀJ is the Fisher information; it is evaluated
at the noiseless prediction (the closed form).  Where the Jacobian itself depends on the
noisy data (the contact flags, the filtered fingertip velocity), :func:`expected_information`
can average F over ``noise_samples`` noisy sensor draws of the prediction instead.

The prediction (cheap, see :data:`PREDICT_SUBSTEPS`): the poking finger starts at the
approach start point (the transit before it touches nothing and teaches nothing), moves
in a straight line for the approach, and holds still for :data:`HOLD_TIME`; the retreat
is left out (the finger leaves the surface).  Ground impulses are not reported by the
physics engine per vertex: they are the non-negative least-squares fit of the model's
residuals at the predicted states (the estimator's first "impulses" stage, per sample;
exact because the residuals are linear in them); finger impulses are the simulated ones.

The quasi-static identity-Jacobian approximation (:meth:`ExpectedInformation.identity`)
skips the dynamics: the object is assumed not to respond to the poke in a way that
depends on θ (∂x_t/∂θ = 0) and to move rigidly with the start pose (∂x_t/∂s = I), so each
sample's measurement residuals (normal, contact flag, pose observation) contribute
J_tᵀJ_t with J_t = [∂r_t/∂θ, ∂r_t/∂q_{t-1} + ∂r_t/∂q_t] (a fingertip's contact frame is
that of the interval's middle) along the predicted contact sequence; forces
(which only the dynamics connect to θ) add nothing.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.sparse as sp

from tacest.constants import STANDARD_GRAVITY
from tacest.errors import TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import Scales, data_matrix, global_vector, touching
from tacest.estimation.uncertainty import schur_information
from tacest.geometry.polygon import polygon_inertia, signed_area
from tacest.geometry.shapes import Shape, make_shape
from tacest.interrupt import deferred_interrupts
from tacest.io.run import Run
from tacest.model.jacobians2d import (KINEMATICS_SIGMA, contact_state_function, stage_active_weights,
                                      stage_residual_jacobian, start_residual_jacobian)
from tacest.model.priors import friction_information
from tacest.model.stage2d import START_TERM_OUTPUTS, SQUARED_TERMS, TERMS, StageModel2D, stage_local_variables
from tacest.sim.pokes import CLEARANCE  # no pymunk: the one definition of the approach clearance

#: physics substeps per sample of a prediction: 1 ms at 100 Hz.  The recorder uses at
#: least 20 (0.5 ms) for accurate force streams; the information depends on the
#: contact sequence and the trajectory to first order only, and halving the substeps
#: changes the logdet score of a poke by a few per cent (docs/planning.md), far less
#: than the differences between candidate pokes
PREDICT_SUBSTEPS = 10
#: s, the fingers hold still this long after the approach (the object comes to rest)
HOLD_TIME = 0.2

#: Gauss–Newton steps of the ground-impulse fit (ExpectedInformation._fit_ground): the
#: whitened residuals are linear in the impulses but for the smooth friction-cone
#: penalties; 3 steps bring the fitted residual to within 1e-5 (relative) of 10 steps on the
#: test pokes of tests/test_planning.py
GROUND_FIT_ITERATIONS = 3
#: weight (relative to the largest column norm of a sample's impulse Jacobian) of the
#: tangential ground impulses in the ground-impulse fit.  The fit is degenerate: a
#: sticking object's friction can be split among its resting vertices in many ways, and
#: non-negative least squares returns a basic solution, with vertices on an edge of their
#: friction cone.  There the cone penalty's slope is that of a limit being reached, and
#: its derivative with respect to mu_ground (∝ the normal impulse) is information about
#: the ground friction that a sticking contact does not hold (a finger pressing a resting
#: box from above was predicted to pin the ground friction down ten-fold; the recorded
#: pokes then showed none, and the planner asked for the same poke again and again).
#: The small penalty picks the fit with the least tangential impulse (friction split
#: evenly, inside the cone); 1e-3 changes the fitted residual by ~1e-6 relative (its
#: square), far below the noise, and a sliding contact, which the dynamics hold on the
#: cone's edge, stays there
GROUND_FIT_TANGENTIAL_WEIGHT = 1e-3
#: measurement terms used by the identity-Jacobian approximation
MEASUREMENT_TERMS = ("force", "normal", "contact", "pose")


# ---------------------------------------------------------------------------------
# the estimate as a model


def planning_inputs(est, runs: list, dim: int, shape_of) -> tuple:
    """(shape, vertices (K, dim) m body frame, the last run) of an estimate to plan from,
    after the checks of both dimensions: a ``dim``-D estimate, its runs given (same
    number, dimension and lengths), fingers to poke with, vertices of its shape
    (``shape_of(spec)``).  TacestError (one line, naming the file) otherwise."""
    name = est.filename or "estimate"
    if est.dim != dim:
        raise TacestError(f"{name}: is a {est.dim}-D estimate; the {dim}-D planner needs a {dim}-D one")
    if len(runs) != len(est.runs):
        raise TacestError(f"{name} holds {len(est.runs)} run(s) but {len(runs)} run file(s) were given; give the "
                          "runs it was estimated from")
    for i, (re_, run) in enumerate(zip(est.runs, runs)):
        if run.dim != dim:
            raise TacestError(f"{run.filename or 'run'}: is a {run.dim}-D run; a {dim}-D estimate needs {dim}-D runs")
        if re_.pose.shape[0] != run.n_samples:
            raise TacestError(f"{run.filename or 'run'}: has {run.n_samples} samples but run {i} of {name} has "
                              f"{re_.pose.shape[0]}; it is not the run the estimate was made from (re-estimate "
                              "after appending)")
    run = runs[-1]
    if run.n_fingers == 0:
        raise TacestError(f"{run.filename or 'run'}: has no fingers, so there is nothing to poke with")
    shape = shape_of(est.shape)
    V = np.asarray(est.vertices, float)
    if V.shape != (shape.n_vertices, dim):
        raise TacestError(f"{name}: /params/vertices has shape {V.shape}, expected ({shape.n_vertices}, {dim}) "
                          f"for shape {est.shape}")
    return shape, V, run


@dataclass
class ModelState:
    """What an estimate says about the object now.

    shape : Shape parameterization (box, polygon:K) of the estimate; vertices : (K, 2) m,
    body frame, in the parameterization's vertex order; mass : kg; inertia : kg·m²;
    friction_ground, friction_finger; pose : (3,) [x m, y m, angle rad] at the end of
    the last run; p_finger__world : (F, 2) m, fingertips at the end of the last run;
    finger_radius : (F,) m; dt : s; has_force : the runs have a force stream;
    pose_sigma : (sigma_position m, sigma_angle rad) if the runs have pose observations,
    else None; up : (2,) ground normal; ground_height : m.
    """

    shape: Shape
    vertices: np.ndarray
    mass: float
    inertia: float
    friction_ground: float
    friction_finger: float
    pose: np.ndarray
    p_finger__world: np.ndarray
    finger_radius: np.ndarray
    dt: float
    has_force: bool = True
    pose_sigma: tuple | None = None
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0]))
    ground_height: float = 0.0

    @property
    def n_fingers(self) -> int:
        return int(len(self.finger_radius))

    @property
    def centroid__world(self) -> np.ndarray:
        """(2,) m: the estimated centre of mass (the shape's centroid) now."""
        return np.asarray(self.pose[:2], float).copy()

    @classmethod
    def from_estimate(cls, est, runs: list[Run]) -> "ModelState":
        """The object of an Estimate (tacest.io.estimate) at the end of its last run.

        runs : the run files it was estimated from (same number and order), for the
        fingers, dt and streams.  TacestError when they do not fit together.
        """
        shape, V, run = planning_inputs(est, runs, 2, make_shape)
        p = est.params
        for k in ("mass", "inertia", "friction_ground", "friction_finger"):
            v = float(p[k])
            if not (math.isfinite(v) and v > 0):
                raise TacestError(f"{est.filename or 'estimate'}: /params attrs {k} = {v} is not > 0")
        pose = np.asarray(est.runs[-1].pose[-1], float)
        if not np.all(np.isfinite(pose)):
            raise TacestError(f"{est.filename or 'estimate'}: the last pose of the last run is not finite")
        fp = np.asarray(run.finger_position[-1], float)
        pose_sigma = (float(run.sigma_position), float(run.sigma_angle)) if run.has_pose_obs else None
        return cls(shape=shape, vertices=V, mass=float(p["mass"]), inertia=float(p["inertia"]),
                   friction_ground=float(p["friction_ground"]), friction_finger=float(p["friction_finger"]),
                   pose=pose, p_finger__world=fp, finger_radius=np.asarray(run.finger_radius, float).copy(),
                   dt=float(run.dt), has_force=run.has_force, pose_sigma=pose_sigma,
                   up=np.asarray(run.up, float), ground_height=float(run.ground_height))

    def sim_object(self):
        """The estimate as a tacest.sim SimObject (counter-clockwise vertices)."""
        from tacest.sim.objects import SimObject

        V = self.vertices if signed_area(self.vertices) > 0 else self.vertices[::-1].copy()
        return SimObject(vertices=V.copy(), mass=self.mass, inertia=self.inertia,
                         friction_ground=self.friction_ground, friction_finger=self.friction_finger,
                         shape=self.shape.name)


# ---------------------------------------------------------------------------------
# prediction


@dataclass
class PredictedPoke:
    """A noiseless simulated poke (T samples, F fingers); sample 0 is the start state.

    pose : (T, 3) COM pose; p_finger__world : (T, F, 2) m; contact : (T, F) bool;
    impulse__world : (T, F, 2) N·s of each finger ON the object per interval;
    normal__world : (T, F, 2) unit, NaN where no contact; dt : s;
    action : (6,) poke vector (tacest.sim.pokes.POKE_NAMES).
    """

    pose: np.ndarray
    p_finger__world: np.ndarray
    contact: np.ndarray
    impulse__world: np.ndarray
    normal__world: np.ndarray
    dt: float
    action: np.ndarray

    @property
    def n_samples(self) -> int:
        return int(self.pose.shape[0])

    def to_run(self, model: ModelState, noise=None, rng=None) -> Run:
        """The prediction as a Run with the model's streams.  noise : optional
        (force N, normal rad, position m) sigmas of a noisy sensor draw (rng)."""
        T, F, _ = self.p_finger__world.shape
        on = self.contact.astype(bool)
        force = self.impulse__world / self.dt
        normal = self.normal__world.copy()
        fp = self.p_finger__world.copy()
        if noise is not None:
            sf, sn, s_pos = noise
            force = np.where(on[..., None], force + rng.normal(size=force.shape) * sf, 0.0)
            a = rng.normal(size=(T, F)) * sn
            c, s = np.cos(a), np.sin(a)
            normal = np.stack([c * normal[..., 0] - s * normal[..., 1], s * normal[..., 0] + c * normal[..., 1]], -1)
            fp = fp + rng.normal(size=fp.shape) * s_pos
        normal = np.where(on[..., None], normal, np.nan)
        run = Run(dim=2, dt=self.dt, time=self.dt * np.arange(T), gravity=-STANDARD_GRAVITY * model.up, source="prediction",
                  finger_position=fp, finger_radius=model.finger_radius.copy(),
                  contact=on.astype(np.uint8), force=force if model.has_force else None, normal=normal,
                  ground_height=model.ground_height, ground_normal=model.up.copy())
        if model.pose_sigma is not None:
            run.pose_obs = self.pose.copy()
            run.sigma_position, run.sigma_angle = model.pose_sigma
        return run


@deferred_interrupts()  # Ctrl-C in a substep's cffi callback would be lost (tacest.interrupt)
def predict_poke(model: ModelState, action, substeps: int = PREDICT_SUBSTEPS, hold_time: float = HOLD_TIME,
                 settle_time: float = 0.05, effects=()) -> PredictedPoke:
    """Simulate one poke (a (6,) POKE_NAMES vector) on the estimated object, noiseless.
    effects : resolved tacest.sim.effects.Effect of the world to simulate besides the
    estimate (the physical ones act in the world, com_offset moves the COM; sensor and
    clock effects are the caller's: tacest.sim.record.sensor_streams).

    The object starts at rest at the model's pose, lowered (or raised) so that its
    lowest vertex touches the ground, and settles for ``settle_time`` s (unrecorded;
    the estimate's pose is consistent with the ground only to the contact tolerance).
    The poking finger starts at ``target + d·(s_touch + CLEARANCE)``, idle fingers
    are parked above the object; the approach is a straight line to
    ``target + d·(s_touch − depth)`` at ``speed``, then the fingers hold for ``hold_time``.
    """
    from tacest.geometry.transforms import rot2
    from tacest.sim.pokes import Poke
    from tacest.sim.world import World

    from tacest.sim.effects import find
    from tacest.sim.objects import apply_com_offset

    poke = Poke.from_vector(action, model.n_fingers)
    obj = model.sim_object()
    com = find(effects, "com_offset")
    if com is not None:
        obj = apply_com_offset(obj, com["dx"], com["dy"])
    pose = np.asarray(model.pose, float).copy()
    up = model.up
    low = float(np.min((obj.vertices @ rot2(pose[2]).T + pose[:2]) @ up)) - model.ground_height
    pose[:2] -= low * up
    radius = model.finger_radius
    top = float(np.max((obj.vertices @ rot2(pose[2]).T + pose[:2])[:, 1]))
    # every finger away from the object while the world settles
    parked = np.asarray(model.p_finger__world, float).copy()
    parked[:, 1] = np.maximum(parked[:, 1], top + radius + 0.02)
    world = World(obj, pose, np.zeros(3), parked, radius, effects=effects)
    d = poke.direction__world
    reach = 0.3 + float(np.max(radius))
    s = world.touch_distance(poke.target__world - reach * d, d, radius[poke.finger], reach=2 * reach)
    s_touch = 0.0 if s is None else s - reach
    start = poke.target__world + d * (s_touch + CLEARANCE)
    end = poke.target__world + d * (s_touch - poke.depth)
    dt = model.dt
    h = dt / int(substeps)
    hold = world.p_control__world
    for _ in range(int(round(settle_time / h))):
        world.step(hold, h)
    # put the poking finger at the approach start (teleport both bodies)
    f = poke.finger
    world.fingers[f].position = tuple(map(float, start))
    world.fingers[f].velocity = (0.0, 0.0)
    world.controls[f].position = tuple(map(float, start))
    world.take_measurement()
    duration = float(np.linalg.norm(end - start)) / poke.speed
    n_samples = int(math.ceil((duration + hold_time) / dt - 1e-9))
    T = n_samples + 1
    F = model.n_fingers
    poses = np.empty((T, 3))
    fps = np.empty((T, F, 2))
    contact = np.zeros((T, F), bool)
    imp = np.zeros((T, F, 2))
    nrm = np.full((T, F, 2), np.nan)
    poses[0] = world.pose
    fps[0] = world.p_finger__world
    ctl = world.p_control__world.copy()
    for k in range(1, T):
        for j in range(int(substeps)):
            t = ((k - 1) * int(substeps) + j + 1) * h
            ctl[f] = start + (end - start) * min(t / duration, 1.0)
            world.step(ctl, h)
        m = world.take_measurement()
        poses[k] = world.pose
        fps[k] = world.p_finger__world
        contact[k], imp[k], nrm[k] = m.contact, m.impulse__world, m.normal__world
    # angles continue the model's (pymunk's angle is continuous within the rollout)
    return PredictedPoke(pose=poses, p_finger__world=fps, contact=contact, impulse__world=imp,
                         normal__world=nrm, dt=dt, action=poke.to_vector())


# ---------------------------------------------------------------------------------
# the linearized residuals of one predicted poke


def theta_of_model(model: ModelState, L: float, m0: float) -> np.ndarray:
    """Scaled parameters θ (as the estimator's decision vector) of the model's object:
    [shape s (n_s), log(m/m0), log(I / I_uniform), mu_ground, mu_finger]."""
    shape = model.shape
    V = np.asarray(model.vertices, float)
    if shape.name == "box":
        s = np.array([np.ptp(V[:, 0]), np.ptp(V[:, 1])]) / L
    else:
        s = V.reshape(-1) / L  # raw vertices (x0, y0, x1, y1, ...); the centroid is already 0
    I_uniform = polygon_inertia(V if signed_area(V) > 0 else V[::-1], model.mass)
    return np.concatenate([s, [math.log(model.mass / m0), math.log(model.inertia / I_uniform),
                               model.friction_ground, model.friction_finger]])


def information_names_for(shape: Shape) -> list:
    """Row names of I_obs and F (as tacest.estimation.uncertainty.information_names_2d)."""
    if shape.name == "box":
        shape_names = ["width", "height"]
    else:
        shape_names = [f"vertex{k}_{c}" for k in range(shape.n_vertices) for c in "xy"]
    return shape_names + ["mass", "inertia_log_ratio", "friction_ground", "friction_finger",
                          "final_x", "final_y", "final_angle"]


class _Buffered:
    """A CasADi Function evaluated on bound numpy buffers (Function.buffer): no DM
    conversion, which costs ~20x the evaluation itself for the mapped Jacobians here.
    Every input and output must be dense; outputs come back as (rows, cols) arrays."""

    def __init__(self, fun):
        self.fun = fun
        for i in range(fun.n_in()):
            assert fun.sparsity_in(i).is_dense(), fun.name_in(i)
        for i in range(fun.n_out()):
            assert fun.sparsity_out(i).is_dense(), fun.name_out(i)
        self.buf, self._run = fun.buffer()
        self.ins = [np.zeros(fun.nnz_in(i)) for i in range(fun.n_in())]
        self.outs = [np.zeros(fun.nnz_out(i)) for i in range(fun.n_out())]
        for i, a in enumerate(self.ins):
            self.buf.set_arg(i, memoryview(a))
        for i, a in enumerate(self.outs):
            self.buf.set_res(i, memoryview(a))

    def __call__(self, *args):
        for a, x in zip(self.ins, args):
            a[:] = np.asarray(x, float).reshape(-1, order="F")  # column-major nonzeros
        self._run()
        if self.buf.ret() != 0:
            raise TacestError(f"internal: evaluating {self.fun.name()} failed")
        return [o.reshape(self.fun.size_out(i), order="F").copy() for i, o in enumerate(self.outs)]


@dataclass
class Linearization:
    """The linearized residuals of one predicted poke (scaled units, as the estimator's).

    Ja : (R, n_theta + 3) dense Jacobian columns of θ and of the start pose s = Q[:, 0];
    Jx : (R, n_x) sparse Jacobian of the nuisance variables, in the order V[:, 0..T-1],
    Q[:, 1..T-1], ground impulses (K per interval), finger impulses (2F per interval,
    only where the predicted tactile flag is 1); r : (R,) residuals; the point:
    theta (n_theta,), Q, V (3, T), LG (n_lg, T-1) (the estimator's ground impulses per
    interval), LF (2F, T-1); run : the predicted Run.
    """

    Ja: np.ndarray
    Jx: object
    r: np.ndarray
    theta: np.ndarray
    Q: np.ndarray
    V: np.ndarray
    LG: np.ndarray
    LF: np.ndarray
    run: Run


class ExpectedInformation:
    """Expected information of predicted pokes for one model structure.

    Built once per (shape, fingers, config): the per-sample residual Jacobian functions
    (CasADi SX, from the estimator's own stage and start functions) are reused for every
    candidate; only their mapped versions are cached per prediction length.

    Parameters
    ----------
    shape_spec : estimate shape string (``box``, ``polygon:K``); n_fingers : F;
    config : EstimatorConfig of the estimate (noise levels, weights, homotopy);
    L, m0 : the estimator's length (m) and mass (kg) scales.
    """

    def __init__(self, shape_spec: str, n_fingers: int, config: EstimatorConfig, L: float, m0: float):
        self.shape = make_shape(shape_spec)
        self.F = int(n_fingers)
        self.config = config
        self.L, self.m0 = float(L), float(m0)
        # the plain model (no effects; no Occam term: predictions have no pose observations)
        self.model = StageModel2D(self.shape, reach_on=config.noise.complementarity_reach > 0)
        pr = self.model
        self.K = pr.K
        self.n_theta = pr.n_theta
        self.n_shape = pr.n_shape
        self.names = information_names_for(self.shape)
        self._build()
        self._mapped = {}

    # -- CasADi functions, once -----------------------------------------------------
    def _build(self):
        pr = self.model
        stage, start = pr.stage_function(self.F), pr.start_function(self.F)
        ins = stage.sx_in()
        qp, vp, q, v, lg, lf, phys, d, g, _, _ = ins  # the plain model: no states
        w = ca.SX.sym("w", len(TERMS))
        out = dict(zip(stage.name_out(), stage(*ins)))
        rows = {t: ca.sqrt(w[TERMS.index(t)]) * ca.vec(out[t]) for t in SQUARED_TERMS}
        r = ca.vertcat(*[rows[t] for t in SQUARED_TERMS], out["g_kin"] / KINEMATICS_SIGMA)
        self.n_y = stage_local_variables(ins).shape[0]
        # ground impulses per interval, as the estimator lays them out: [lambda_n (K)] or
        # [lambda_n (K), lambda_t (K)]; the normal ones are >= 0, tangential ones free
        self.n_lg = lg.shape[0]
        if self.n_lg not in (self.K, 2 * self.K):
            raise TacestError(f"internal: {self.n_lg} ground impulses per interval for {self.K} vertices")
        self.lg_nonneg = np.arange(self.n_lg) < self.K
        self.stage_rj = stage_residual_jacobian(stage)
        self.contact_state = contact_state_function(stage)
        self.stage_r_lg = ca.Function("stage_r_lg", [qp, vp, q, v, lg, lf, phys, d, g, w],
                                      [ca.densify(r), ca.densify(ca.jacobian(r, lg))])
        # the measurement rows only, for the identity-Jacobian approximation (w.r.t. the
        # rigid shift s of every pose, ∂q_prev/∂s = ∂q/∂s = I: a fingertip's contact frame
        # is the interval's middle, so both ends count; and phys)
        rm = ca.vertcat(*[rows[t] for t in MEASUREMENT_TERMS])
        self.stage_meas = ca.Function("stage_meas", [qp, vp, q, v, lg, lf, phys, d, g, w],
                                      [ca.densify(ca.horzcat(ca.jacobian(rm, q) + ca.jacobian(rm, qp),
                                                             ca.jacobian(rm, phys)))])
        self.start_rj = start_residual_jacobian(start)
        # the term of every row of stage_rj (then its kinematics and active-set rows) and
        # of start_rj, as jacobians2d stacks them
        size = lambda f, name: int(np.prod(f.size_out(name)))  # noqa: E731
        self.row_terms = (np.array([t for t in SQUARED_TERMS for _ in range(size(stage, t))]
                                   + ["kinematics"] * int(out["g_kin"].numel()) + ["active"] * (2 * self.K), object),
                          np.array([t for t, name in START_TERM_OUTPUTS for _ in range(size(start, name))], object))
        th = ca.SX.sym("theta", self.n_theta)
        self.phys_of_theta = ca.Function("phys_jac", [th], [pr.phys_sx(th, self.L, self.m0),
                                                            ca.densify(ca.jacobian(pr.phys_sx(th, self.L, self.m0),
                                                                                   th))])

    def _call(self, fun, N, *args):
        """Evaluate ``fun`` mapped over N samples (inputs (n, N) or (n,) arrays, outputs
        (m, N·k) arrays): a cached :class:`_Buffered` evaluator per (function, N)."""
        key = (fun.name(), N)
        if key not in self._mapped:
            self._mapped[key] = _Buffered(fun.map(N) if N != 1 else fun)
        return self._mapped[key](*args)

    # -- data of a prediction -------------------------------------------------------
    def _data(self, run: Run):
        eps, comp_mult, dyn_mult = self.config.solver.homotopy[-1]
        g = global_vector(run, Scales(L=self.L, m0=self.m0, g=STANDARD_GRAVITY), self.config, eps, comp_mult,
                          dyn_mult)
        D = data_matrix(run, self.F).T  # (n_data, T)
        w = np.array([getattr(self.config.weights, t) for t in TERMS], float)
        return g, D, w

    def _states(self, pred: PredictedPoke):
        """Scaled Q (3, T), V (3, T) (backward differences, eq. D2), LF (2F, T-1)."""
        scale = np.array([self.L, self.L, 1.0])
        Q = (pred.pose / scale).T
        Vv = np.zeros_like(Q)
        Vv[:, 1:] = np.diff(Q, axis=1) / pred.dt
        Lam = self.m0 * STANDARD_GRAVITY * pred.dt  # the prediction's world has standard gravity
        LF = (pred.impulse__world[1:] / Lam).reshape(pred.n_samples - 1, -1).T
        return Q, Vv, LF

    def linearize(self, model: ModelState, pred: PredictedPoke, run: Run | None = None) -> "Linearization":
        """Whitened residuals of a predicted poke and their Jacobian at the prediction
        (ground impulses fitted): a :class:`Linearization`."""
        run = run or pred.to_run(model)
        T = pred.n_samples
        g, D, w = self._data(run)
        theta = theta_of_model(model, self.L, self.m0)
        phys, dphys = self._call(self.phys_of_theta, 1, theta)
        phys = phys.reshape(-1)
        Q, Vv, LF = self._states(pred)
        N = T - 1
        no_plate = np.zeros((0, N))
        args = [Q[:, :-1], Vv[:, :-1], Q[:, 1:], Vv[:, 1:], np.zeros((self.n_lg, N)), LF,
                np.repeat(phys[:, None], N, 1), D[:, 1:], np.repeat(g[:, None], N, 1), np.repeat(w[:, None], N, 1)]
        args[4] = LG = self._fit_ground(args, N, model.friction_ground)
        stage_args = args[:9] + [no_plate, no_plate]
        a = stage_active_weights(lambda *x: self._call(self.contact_state, N, *x), N, stage_args, self.K)
        r, J = self._call(self.stage_rj, N, *stage_args, args[9], a)
        n_r = r.shape[0]
        J = J.reshape(n_r, N, self.n_y)
        r0, J0 = self._call(self.start_rj, 1, Q[:, 0], Vv[:, 0], phys, D[:, 0], g, np.zeros(0), w)
        Ja, Jx, r_all = self._assemble(J, r, J0, r0.reshape(-1), dphys, T, run)
        return Linearization(Ja=Ja, Jx=Jx, r=r_all, theta=theta, Q=Q, V=Vv, LG=LG, LF=LF, run=run)

    def _fit_ground(self, args, N, mu_ground: float, iterations: int = GROUND_FIT_ITERATIONS) -> np.ndarray:
        """(n_lg, N) ground impulses minimizing the whitened residuals at the predicted
        states, per sample, inside the friction cone of ``mu_ground``.

        With normal and tangential impulses the cone of each vertex is spanned by its
        two edges, (λ_n, λ_t) = α (1, μ) + β (1, −μ) with α, β >= 0, so each step is a
        non-negative least-squares problem in (α, β); with normal impulses alone it is
        one in λ_n.  The residuals are linear in the impulses except the smooth one-sided
        cone penalties, which are nearly constant inside the cone: the steps re-linearize
        there.
        """
        from scipy.optimize import nnls

        K = self.K
        if self.n_lg == 2 * K:
            I_K = np.eye(K)
            M = np.block([[I_K, I_K], [mu_ground * I_K, -mu_ground * I_K]])
            T_rows = M[K:]  # C -> tangential impulses
        else:
            M = np.eye(self.n_lg)
            T_rows = np.zeros((0, M.shape[1]))
        C = np.zeros((M.shape[1], N))
        for _ in range(iterations):
            args[4] = M @ C
            r, J_lg = self._call(self.stage_r_lg, N, *args)  # (n_r, N), (n_r, N·n_lg)
            n_r = r.shape[0]
            J_lg = J_lg.reshape(n_r, N, self.n_lg)
            for t in range(N):
                A = J_lg[:, t, :] @ M
                if not np.any(A):
                    continue
                b = A @ C[:, t] - r[:, t]
                if len(T_rows) and GROUND_FIT_TANGENTIAL_WEIGHT > 0:
                    # the least tangential impulse among (near-)equal fits: a sticking
                    # contact is fitted inside its cone, not on an edge of it
                    wt = GROUND_FIT_TANGENTIAL_WEIGHT * float(np.linalg.norm(A, axis=0).max())
                    A = np.vstack([A, wt * T_rows])
                    b = np.concatenate([b, np.zeros(len(T_rows))])
                C[:, t] = nnls(A, b, maxiter=50 * M.shape[1])[0]
        return M @ C

    def _assemble(self, J, r, J0, r0, dphys, T, run):
        """Global Jacobian of a prediction from the per-sample blocks J (n_r, N, n_y) and
        the start block J0 (n_0, 3 + 3 + n_phys): kept columns Ja (θ through the lifted
        physical quantities, start pose), nuisance columns Jx (sparse, layout of
        :class:`Linearization`).  Rows: sample 1's residuals, ..., sample N's, then sample 0's."""
        F = self.F
        N = T - 1
        n_r = J.shape[0]
        n_phys = dphys.shape[0]
        n_lg = self.n_lg
        n_loc = 12 + n_lg + 2 * F  # y = [q_prev 3, v_prev 3, q 3, v 3, lg n_lg, lf 2F] + phys
        # nuisance layout: V (3T), Q[1:] (3(T-1)), LG (n_lg N), LF (2F N); kept: theta, Q[0]
        iLG = 6 * T - 3
        iLF = iLG + n_lg * N
        n_x = iLF + 2 * F * N
        t = np.arange(1, T)[:, None]  # sample index of each block
        col = np.concatenate([3 * T + 3 * (t - 2) + np.arange(3),  # q_prev = Q[t-1] (t-1 >= 1)
                              3 * (t - 1) + np.arange(3),  # v_prev = V[t-1]
                              3 * T + 3 * (t - 1) + np.arange(3),  # q = Q[t]
                              3 * t + np.arange(3),  # v = V[t]
                              iLG + n_lg * (t - 1) + np.arange(n_lg),
                              iLF + 2 * F * (t - 1) + np.arange(2 * F)], axis=1)  # (N, n_loc)
        col[0, 0:3] = -1  # Q[0] is kept, not nuisance
        rows_all = (np.arange(N)[None, :, None] * n_r + np.arange(n_r)[:, None, None])  # (n_r, N, 1)
        Jl = J[:, :, :n_loc]
        mask = (col[None, :, :] >= 0) & (Jl != 0)
        rr = np.broadcast_to(rows_all, Jl.shape)[mask]
        cc = np.broadcast_to(col[None, :, :], Jl.shape)[mask]
        vv = Jl[mask]
        n_0 = len(r0)
        Ja = np.zeros((n_r * N + n_0, self.n_theta + 3))
        Ja[:n_r * N, :self.n_theta] = np.einsum("inp,pk->nik", J[:, :, n_loc:], dphys).reshape(N * n_r, -1)
        Ja[:n_r, self.n_theta:] = J[:, 0, 0:3]
        base = n_r * N
        J0 = np.asarray(J0).reshape(n_0, -1)
        Ja[base:, self.n_theta:] = J0[:, 0:3]
        Ja[base:, :self.n_theta] = J0[:, 6:6 + n_phys] @ dphys
        i0, j0 = np.nonzero(J0[:, 3:6])  # v = V[0]
        Jx = sp.csc_matrix((np.concatenate([vv, J0[:, 3:6][i0, j0]]),
                            (np.concatenate([rr, base + i0]), np.concatenate([cc, j0]))), shape=(Ja.shape[0], n_x))
        # finger impulses are fixed at 0 where the predicted tactile flag is 0 (as the
        # estimator's bounds do): they are no variables there
        on = touching(run)[1:]  # (N, F)
        free = np.ones(n_x, bool)
        free[iLF:] = np.repeat(on, 2, axis=1).reshape(-1)
        Jx = Jx[:, np.nonzero(free)[0]]
        return Ja, Jx, np.concatenate([r.T.reshape(-1), r0])

    # -- information ------------------------------------------------------------------
    def to_physical(self, I_scaled: np.ndarray, model: ModelState) -> np.ndarray:
        """Scaled (θ, s) information -> physical units (uncertainty.py's convention):
        lengths m, mass kg, inertia log ratio, friction, pose m / rad."""
        d = np.ones(self.n_theta + 3)
        d[: self.n_shape] = 1.0 / self.L
        d[self.n_shape] = 1.0 / model.mass  # d log m / d m
        d[self.n_theta: self.n_theta + 2] = 1.0 / self.L
        I_phys = I_scaled * np.outer(d, d)
        if not model.has_force:  # the estimator fixes the mass without a force stream
            k = self.n_shape
            I_phys[k, :] = 0.0
            I_phys[:, k] = 0.0
        return 0.5 * (I_phys + I_phys.T)

    def fisher(self, model: ModelState, pred: PredictedPoke, run: Run | None = None) -> np.ndarray:
        """F (n, n), physical units, rows :attr:`names`: Schur complement of JᵀJ onto (θ, s)."""
        lin = self.linearize(model, pred, run)
        return self.to_physical(schur_information(lin.Ja, lin.Jx), model)

    def linearized(self, model: ModelState, pred: PredictedPoke, run: Run | None = None):
        """The prediction's residuals as a tacest.information.sensitivity.Linearized:
        rows measured (MEASUREMENT_TERMS) or driving (the physics, kinematics and
        active-set rows); ∂x/∂s of the identity approximation: every later pose moves
        with the start pose (∂q_t/∂s = I), velocities and impulses do not; the
        transition's weak prior on the contact impulses (sensitivity.impulse_prior).
        The residuals are used linearized (no ``residual_at``)."""
        from tacest.information.sensitivity import Linearized, impulse_prior

        lin = self.linearize(model, pred, run)
        T = pred.n_samples
        N = T - 1
        stage_terms, start_terms = self.row_terms
        term = np.concatenate([np.tile(stage_terms, N), start_terms])
        sample = np.concatenate([np.repeat(np.arange(1, T), len(stage_terms)), np.zeros(len(start_terms), int)])
        iLG = 6 * T - 3  # nuisance layout of Linearization: V (3T), Q[1:] (3(T-1)), LG, LF
        iLF = iLG + self.n_lg * N
        free = np.ones(iLF + 2 * self.F * N, bool)
        free[iLF:] = np.repeat(touching(lin.run)[1:], 2, axis=1).reshape(-1)
        S = sp.lil_matrix((len(free), 3))
        for t in range(1, T):
            S[3 * T + 3 * (t - 1) + np.arange(3), np.arange(3)] = 1.0
        prior = np.zeros(len(free))
        prior[iLG:] = impulse_prior(np.concatenate([lin.LG.T.reshape(-1), lin.LF.T.reshape(-1)]))
        measured = np.isin(term, MEASUREMENT_TERMS)
        return Linearized(Ja=lin.Ja, Jx=lin.Jx, r=lin.r, measured=measured, driving=~measured, sample=sample,
                          S_identity=sp.csr_matrix(S)[np.nonzero(free)[0]], n_theta=self.n_theta,
                          x_prior=prior[free], extra={"term": term})

    def sensitivity_information(self, model: ModelState, pred: PredictedPoke, method: str, run: Run | None = None,
                                seed: int = 0) -> np.ndarray:
        """F (n, n), physical units, by a construction of tacest.information.sensitivity
        (``diffsim``, ``marginal``, or ``schur`` / ``identity`` on the same rows)."""
        from tacest.information.sensitivity import information

        return self.to_physical(information(self.linearized(model, pred, run), method, seed=seed), model)

    def identity(self, model: ModelState, pred: PredictedPoke, run: Run | None = None) -> np.ndarray:
        """F_id (n, n), physical units: the quasi-static identity-Jacobian approximation
        (module docstring): Σ_t J_tᵀJ_t of the measurement rows, ∂q_t/∂s = I."""
        run = run or pred.to_run(model)
        T = pred.n_samples
        N = T - 1
        g, D, w = self._data(run)
        theta = theta_of_model(model, self.L, self.m0)
        phys, dphys = self._call(self.phys_of_theta, 1, theta)
        phys = phys.reshape(-1)
        Q, Vv, LF = self._states(pred)
        (J,) = self._call(self.stage_meas, N, Q[:, :-1], Vv[:, :-1], Q[:, 1:], Vv[:, 1:], np.zeros((self.n_lg, N)), LF,
                          np.repeat(phys[:, None], N, 1), D[:, 1:], np.repeat(g[:, None], N, 1),
                          np.repeat(w[:, None], N, 1))
        n_r = J.shape[0]
        J = J.reshape(n_r, N, 3 + len(phys))  # per sample: [q (3), phys]
        Ja = np.concatenate([np.einsum("rnp,pk->nrk", J[:, :, 3:], dphys).reshape(-1, self.n_theta),
                             np.transpose(J[:, :, :3], (1, 0, 2)).reshape(-1, 3)], axis=1)
        return self.to_physical(Ja.T @ Ja, model)


# ---------------------------------------------------------------------------------
# past information


def prior_information(names: list, model: ModelState, config: EstimatorConfig, L: float,
                      size_bound: float = 0.3) -> np.ndarray:
    """(n, n) diagonal information of the estimator's own prior (config.prior), in the
    physical units of :func:`information_names_for`: shape entries 1/(shape_sigma·L)²
    (m⁻²), mass 1/(m·mass_log_sigma)² (a log-normal prior seen at m), inertia log ratio
    1/inertia_log_sigma², frictions tacest.model.priors.friction_information at the
    model's values; the pose has no prior in the estimator: a weak one, position
    1/size_bound² and angle 1/π², keeps the matrix invertible (a direction no data touch
    stays as uncertain as it can be)."""
    pr = config.prior
    diag = []
    for n in names:
        if n in ("width", "height") or n.startswith("vertex"):
            diag.append(1.0 / (pr.shape_sigma * L) ** 2)
        elif n == "mass":
            diag.append(1.0 / (model.mass * pr.mass_log_sigma) ** 2)
        elif n == "inertia_log_ratio":
            diag.append(1.0 / pr.inertia_log_sigma ** 2)
        elif n in ("friction_ground", "friction_finger"):
            diag.append(friction_information(getattr(model, n), pr))
        elif n in ("final_x", "final_y"):
            diag.append(1.0 / size_bound ** 2)
        elif n == "final_angle":
            diag.append(1.0 / math.pi ** 2)
        else:
            raise TacestError(f"information row {n!r} is not one tacest knows")
    return np.diag(diag)


def past_information(est, model: ModelState, config: EstimatorConfig, L: float, names: list) -> np.ndarray:
    """I_past = I_obs (the estimate's /information/observed) + the estimator's prior
    information (:func:`prior_information`), in the row order ``names``.

    An estimate without /information (another program's) counts as the prior alone.
    """
    prior = prior_information(names, model, config, L)
    if est.information is None:
        return prior
    got = [str(n) for n in est.info_names]
    if sorted(got) != sorted(names):
        raise TacestError(f"{est.filename or 'estimate'}: /information/names {got} do not match the "
                          f"parameters of shape {model.shape.name} ({names})")
    idx = [got.index(n) for n in names]
    I_obs = np.asarray(est.information, float)[np.ix_(idx, idx)]
    if not np.all(np.isfinite(I_obs)):
        raise TacestError(f"{est.filename or 'estimate'}: /information/observed has NaN or inf entries")
    I_obs = 0.5 * (I_obs + I_obs.T)
    return I_obs + prior


def config_of_estimate(est) -> EstimatorConfig:
    """The estimator settings an estimate was made with (its ``config`` attr), else
    defaults; with the sensors' noise levels that judged it (its attr ``sensor_noise``:
    tacest.estimation.sensor_noise.judged_config), so that the information of a planned
    poke weighs each stream as the estimate's own information does."""
    from tacest.estimation.config import load_config
    from tacest.estimation.sensor_noise import judged_config

    if not est.config:
        return EstimatorConfig()
    try:
        config = load_config(None, overrides=json.loads(json.dumps(est.config)))
        return judged_config(config, json.loads(est.extra_attrs.get("sensor_noise", "{}")))
    except (TacestError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise TacestError(f"{est.filename or 'estimate'}: attrs config or sensor_noise: {exc}") from None


def expected_information(info: ExpectedInformation, model: ModelState, pred: PredictedPoke,
                         method: str = "fisher", noise_samples: int = 0, noise=None, seed: int = 0) -> np.ndarray:
    """F of one predicted poke: ``method`` ``fisher`` or ``schur`` (Schur complement),
    ``identity``, or ``diffsim`` / ``marginal`` (tacest.information.sensitivity, common
    random numbers ``seed``); with ``noise_samples`` > 0, the mean over that many noisy
    sensor draws (noise = (force N, normal rad, position m) sigmas) instead of the
    noiseless closed form."""
    if method in ("fisher", "schur"):
        fun = info.fisher
    elif method == "identity":
        fun = info.identity
    else:
        def fun(model_, pred_, run_=None):
            return info.sensitivity_information(model_, pred_, method, run_, seed=seed)
    if noise_samples <= 0:
        return fun(model, pred)
    rng = np.random.default_rng(seed)
    return np.mean([fun(model, pred, pred.to_run(model, noise=noise, rng=rng)) for _ in range(noise_samples)], axis=0)

"""The 3-D model run forward: a time-stepping simulator built from the estimator's own
residuals (tacest.model.stage3d.StageModel3D), for rollouts of an estimated (or nominal) model
and for synthetic test data.

One step (t-1 -> t) takes the poses at t-2 and t-1 (and the earlier ones an effect looks
back at: restitution's approach before an impact, StageModel3D.n_poses) and finds the velocity over the
interval (v world m/s, omega_b body rad/s) and the normal ground impulses lambda_n >= 0
(K) that minimise the model's residuals with no observation: the momentum balance (D1,
with the closed-form Coulomb friction of the estimator; made nearly hard by
DYNAMICS_WEIGHT), the penetration and the complementarity terms.  The pose at t follows from the kinematics
(D2): p[t] = p[t-1] + dt v, q[t] = q[t-1] ⊗ exp(omega_b dt / 2).  It is the estimator's
model with zero process noise, so a rollout shows what the estimated parameters predict.
The small problem (6 + K unknowns, lambda_n >= 0) is solved by IPOPT with the exact
Hessian, warm-started from the previous step.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from tacest.constants import STANDARD_GRAVITY
from tacest.dynamics.rigid3d import cholesky_from_inertia, qexp_half, qmul, quat_log_rate
from tacest.errors import SolveFailedError, TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.geometry.shapes3d import Shape3D, make_shape_3d
from tacest.geometry.transforms import quat_conjugate, quat_multiply, quat_to_matrix
from tacest.interrupt import raise_if_interrupted, watch_interrupts
from tacest.model.effect import Scales
from tacest.model.stage3d import DI, G3_NAMES, NP, StageModel3D

#: factor on the whitened dynamics residual in a simulation step: with the estimator's
#: process sigma (5 % of g dt per sample) the momentum balance then holds to ~0.5 % of
#: g dt (0.3 mm/s per step at 6.8 ms), below anything the contact terms trade against it;
#: larger factors make the step's least squares so stiff that IPOPT crawls
DYNAMICS_WEIGHT = 10.0
#: IPOPT per step: tolerance (scaled KKT error; the unknowns are ~1 m/s, ~1 rad/s and
#: ~1 m0 g dt) and iteration limit
STEP_TOL = 1e-9
STEP_MAX_ITER = 300
#: friction fractions of the continuation tried when a step does not converge directly
FRICTION_CONTINUATION = (0.0, 1 / 3, 2 / 3, 1.0)
SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def shape_parameters(shape: Shape3D, vertices) -> np.ndarray:
    """Physical shape parameters (m) of ``vertices`` (K, 3) written by the estimator:
    box extents (ptp along the body axes) or polytope radii (|v_k|)."""
    V = np.asarray(vertices, float)
    if V.shape != (shape.n_vertices, 3):
        raise TacestError(f"{shape.name} needs {shape.n_vertices} vertices, got {V.shape}")
    if shape.name == "box":
        return np.ptp(V, axis=0)
    return np.linalg.norm(V, axis=1)


class TimeStepper3D:
    """Forward simulator of the 3-D model (see module docstring).

    Parameters
    ----------
    shape : Shape3D or spec string (``box``, ``polytope:K``)
    shape_params : (n_s,) m, physical (box extents or polytope radii)
    mass : kg;  inertia : (3, 3) kg·m² about the COM, body frame;  friction : ground mu
    dt : s;  up : (3,) ground normal;  ground_height : m;  gravity : m/s², along -up
    edge_radius : m, radius of a box's rounded edges (the estimate's ``edge_radius``; 0: sharp)
    config : EstimatorConfig (noise levels and the final homotopy stage of [solver3d])
    effect_params : {estimate /params name: physical value} of further 3-D effects to
        simulate (e.g. ``{"linear_drag.b": 0.3}``; tacest.model.registry), or None
    """

    def __init__(self, shape, shape_params, mass, inertia, friction, dt, up=(0.0, 0.0, 1.0), ground_height=0.0,
                 config: EstimatorConfig | None = None, edge_radius=0.0, gravity=STANDARD_GRAVITY,
                 effect_params=None):
        self.shape = make_shape_3d(shape) if isinstance(shape, str) else shape
        self.config = config or EstimatorConfig()
        self.dt = float(dt)
        sp = np.asarray(shape_params, float).reshape(-1)
        self.L = float(np.mean(sp[: 3])) if self.shape.name == "box" else 2.0 * float(np.mean(sp))
        self.m0 = float(mass)
        rounded = self.shape.name == "box" and float(edge_radius) > 0
        named = dict(effect_params or {})
        extra = tuple(dict.fromkeys(k.split(".")[0] for k in named))
        self.model = StageModel3D(self.shape, 0, effects=(("edge_radius",) if rounded else ()) + extra)
        theta = np.zeros(self.model.n_theta)
        theta[: self.model.n_shape] = sp / self.L
        theta[self.model.theta_index("log_mass")] = 0.0
        theta[self.model.n_shape + 1: self.model.n_shape + 7] = cholesky_from_inertia(
            np.asarray(inertia, float) / (mass * self.L ** 2))
        theta[self.model.theta_index("friction_ground")] = float(friction)
        theta[self.model.theta_index("friction_finger")] = float(friction)
        if rounded:
            theta[self.model.theta_index("edge_radius")] = float(edge_radius) / self.L
        sc = Scales(L=self.L, m0=self.m0, g=float(gravity))
        for e in self.model.effect_objects:
            if e.name in extra:
                for name, v in e.scaled(named, sc, self.model.K, float(friction), 3).items():
                    theta[self.model.theta_index(f"{e.name}.{name}")] = v
        self.theta = theta
        nz = self.config.noise
        eps, comp_mult, dyn_mult = self.config.solver3d.homotopy[-1]
        gvals = dict(L=self.L, m0=self.m0, sig_proc=nz.process, sig_pen=nz.penetration, sig_gap=nz.contact_gap,
                     sig_comp=nz.complementarity, eps=eps, comp_mult=comp_mult,
                     dyn_mult=dyn_mult, sig_force=nz.force, sig_normal=nz.normal,
                     sig_diss=nz.dissipation, sig_rest=nz.rest)
        self.g = np.array([gvals[n] for n in G3_NAMES])
        d = np.zeros(self.model.n_d)
        self.gravity = float(gravity)
        up = np.asarray(up, float) / np.linalg.norm(up)
        d[DI["dt"]] = self.dt
        d[DI["Lam"]] = self.m0 * self.gravity * self.dt
        d[DI["grav"]] = self.gravity
        d[DI["gx"]: DI["gz"] + 1] = -self.gravity * up
        d[DI["nx"]: DI["nz"] + 1] = up
        d[DI["h"]] = float(ground_height)
        d[DI["sig_pos"]] = d[DI["sig_ang"]] = 1.0
        d[DI["qw"]] = 1.0
        self.d = d
        self._step_fun = self._build()
        #: number of steps so far whose IPOPT solve did not converge (see :meth:`step`)
        self.unconverged = 0

    def _build(self):
        K = self.model.K
        stage = self.model._stage_function(direct=True)
        past = [ca.SX.sym(f"x_{k}", NP) for k in range(self.model.n_poses - 1)]  # oldest first
        xb = past[-1]
        y = ca.SX.sym("y", 6 + K)  # [v (3) m/s, omega_b (3) rad/s, lambda_n (K) in m0 g dt]
        th = ca.SX.sym("theta", self.model.n_theta)
        d = ca.SX.sym("d", self.model.n_d)
        g = ca.SX.sym("g", len(G3_NAMES))
        dt, L = d[DI["dt"]], g[0]
        q_c = qmul(xb[3:7], qexp_half(y[3:6], dt))
        xc = ca.vertcat(xb[0:3] + dt * y[0:3] / L, q_c)
        out = dict(zip(stage.name_out(), stage(*past, xc, y[6:], ca.SX(0, 1), th, d, g)))
        contact = ca.vertcat(out["penetration"], out["complementarity"])
        par = ca.vertcat(*past, th, d, g)
        self._pose_fun = ca.Function("pose3d_next", [y, par], [xc])
        nlp = {"x": y, "p": par, "f": 0.5 * (DYNAMICS_WEIGHT ** 2 * ca.sumsqr(out["dynamics"]) + ca.sumsqr(contact))}
        return ca.nlpsol("step3d", "ipopt", nlp, {
            "print_time": False,
            "ipopt": {"print_level": 0, "sb": "yes", "tol": STEP_TOL, "max_iter": STEP_MAX_ITER,
                      "mu_strategy": "adaptive", "hessian_approximation": "exact"}})

    def _solve(self, y0, past, theta, lbx):
        par = np.concatenate([*past, theta, self.d, self.g])
        with watch_interrupts() as watch:
            sol = self._step_fun(x0=y0, p=par, lbx=lbx, ubx=np.inf)
        status = self._step_fun.stats()["return_status"]
        raise_if_interrupted(status, watch)
        return np.asarray(sol["x"]).ravel(), status

    def _scaled(self, pose):
        pose = np.asarray(pose, float)
        return np.concatenate([pose[:3] / self.L, pose[3:] / np.linalg.norm(pose[3:])])

    def step(self, pose_a, pose_b, y0=None, earlier=()):
        """Pose (7,) at t from the poses at t-2 and t-1 (and ``earlier``: the poses before
        t-2, oldest first, that the model looks back at, StageModel3D.n_poses - 3 of them;
        missing ones repeat the oldest given pose, as the estimator's windows do at a run's
        start); returns (pose, y) with y the solved [v, omega_b, lambda_n] (a warm start
        for the next step).  A step where IPOPT does not converge (directly nor by
        continuation in friction) keeps its last iterate and is counted in
        ``unconverged``; a non-finite one raises SolveFailedError."""
        xa, xb = self._scaled(pose_a), self._scaled(pose_b)
        need = self.model.n_poses - 3
        earlier = [self._scaled(x) for x in list(earlier)[-need:]] if need else []
        past = [(earlier or [xa])[0]] * (need - len(earlier)) + earlier + [xa, xb]
        K = self.model.K
        if y0 is None:
            v, w = (pose_b[:3] - pose_a[:3]) / self.dt, quat_log_rate(xa[3:], xb[3:], self.dt)
            y0 = np.concatenate([v, w, np.zeros(K)])
        lbx = np.concatenate([np.full(6, -np.inf), np.zeros(K)])
        y, status = self._solve(np.maximum(y0, lbx), past, self.theta, lbx)
        if status not in SUCCESS:
            # stiff friction at a hard impact: continuation from the frictionless step
            k = self.model.theta_index("friction_ground")
            y = np.maximum(y0, lbx)
            for frac in FRICTION_CONTINUATION:
                th = self.theta.copy()
                th[k] *= frac
                y, status = self._solve(y, past, th, lbx)
        if not np.all(np.isfinite(y)):
            raise SolveFailedError(f"simulation step failed: IPOPT {status}")
        self.unconverged += status not in SUCCESS
        par = np.concatenate([*past, self.theta, self.d, self.g])
        xc = np.asarray(self._pose_fun(y, par)).ravel()
        return np.concatenate([xc[:3] * self.L, xc[3:] / np.linalg.norm(xc[3:])]), y

    def rollout(self, pose0, velocity0, T):
        """(T, 7) poses from the initial pose (7,) and velocity (6,) [v world m/s, omega
        world rad/s] at sample 0 (the velocity of the interval ending at sample 0)."""
        pose0 = np.asarray(pose0, float).copy()
        pose0[3:] /= np.linalg.norm(pose0[3:])
        v0 = np.asarray(velocity0, float)
        w_b = quat_to_matrix(pose0[3:]).T @ v0[3:]
        prev = np.concatenate([pose0[:3] - self.dt * v0[:3],
                               quat_multiply(pose0[3:], quat_conjugate(np.asarray(
                                   ca.DM(qexp_half(ca.DM(w_b), self.dt))).ravel()))])
        poses = [pose0]
        window = [prev, pose0]  # the poses before t, oldest first
        y = None
        keep = self.model.n_poses - 1
        for _ in range(T - 1):
            c, y = self.step(window[-2], window[-1], y, earlier=window[:-2])
            poses.append(c)
            window = (window + [c])[-keep:]
        return np.array(poses)

    def impulses(self, y):
        """lambda_n (K,) N·s of a solved step vector y."""
        return np.asarray(y[6:], float) * self.m0 * self.gravity * self.dt


def initial_state(poses, dt, n_fit=4, gravity=(0.0, 0.0, -STANDARD_GRAVITY)):
    """(pose (7,), velocity (6,) [v world, omega world]) at sample 0 of observed poses
    (T, 7), for a rollout: the position by a least-squares parabola of known gravity
    through the first n_fit samples, the rate as the mean of the first n_fit - 1 body
    rates (in free flight the torque-free rate of a near-isotropic body is ~constant)."""
    P = np.asarray(poses, float)[:n_fit]
    t = np.arange(P.shape[0]) * dt
    gvec = np.asarray(gravity, float)
    # p(t) = p0 + v0 t + g t² / 2: solve for p0, v0 per axis
    A = np.stack([np.ones_like(t), t], 1)
    coef, *_ = np.linalg.lstsq(A, P[:, :3] - 0.5 * np.outer(t * t, gvec), rcond=None)
    p0, v0 = coef[0], coef[1]
    w_b = np.mean([quat_log_rate(P[k, 3:], P[k + 1, 3:], dt) for k in range(P.shape[0] - 1)], axis=0)
    q0 = P[0, 3:] / np.linalg.norm(P[0, 3:])
    pose0 = np.concatenate([p0, q0])
    w_world = quat_to_matrix(q0) @ w_b
    return pose0, np.concatenate([v0, w_world])


def simulate_toss(shape, shape_params, mass, inertia, friction, pose0, velocity0, T, dt=0.0068,
                  sigma_position=1e-3, sigma_angle=1e-2, noise_seed=None, config=None, edge_radius=0.0,
                  ground_height=0.0, effect_params=None):
    """A pose-only 3-D run (tacest.io.run.Run, with /truth) of an object tossed from
    ``pose0`` (7,) with ``velocity0`` (6,) [v world m/s, omega world rad/s], simulated
    for T samples by :class:`TimeStepper3D`.  The observed poses are the simulated ones,
    plus Gaussian noise of the given sigmas (position m; orientation rad, a random
    rotation vector) when ``noise_seed`` is an integer.  The run's extra attribute
    ``simulation_unconverged_steps`` counts the steps that did not converge.  ``edge_radius``
    (m) rounds a box's edges; ``ground_height`` (m) is where the simulated ground is (the
    run file still says 0: a ground offset the estimator has to find); ``effect_params``
    as :class:`TimeStepper3D`'s (in /truth attrs effects)."""
    from tacest.geometry.transforms import quat_from_axis_angle
    from tacest.io.run import Run, Truth

    sim = TimeStepper3D(shape, shape_params, mass, inertia, friction, dt, config=config, edge_radius=edge_radius,
                        ground_height=ground_height, effect_params=effect_params)
    truth_pose = sim.rollout(pose0, velocity0, T)
    attrs = {"simulation_unconverged_steps": int(sim.unconverged), "simulation_edge_radius": float(edge_radius),
             "simulation_ground_height": float(ground_height)}
    obs = truth_pose.copy()
    if noise_seed is not None:
        rng = np.random.default_rng(noise_seed)
        obs[:, :3] += rng.normal(scale=sigma_position, size=(T, 3))
        rv = rng.normal(scale=sigma_angle, size=(T, 3))
        angle = np.linalg.norm(rv, axis=1)
        dq = quat_from_axis_angle(rv / np.maximum(angle, 1e-15)[:, None], angle)
        obs[:, 3:] = quat_multiply(obs[:, 3:], dq)
    V = _vertices(sim.shape, shape_params)
    return Run(dim=3, dt=float(dt), time=np.arange(T) * float(dt), gravity=np.array([0.0, 0.0, -sim.gravity]),
               source="sim-rollout3d", pose_obs=obs, sigma_position=float(sigma_position),
               sigma_angle=float(sigma_angle), ground_height=0.0, ground_normal=np.array([0.0, 0.0, 1.0]),
               prior={"size_bound": float(4 * np.max(shape_params))}, extra_attrs=attrs,
               truth=Truth(pose=truth_pose, vertices=V, mass=float(mass), inertia=np.asarray(inertia, float),
                           # no finger takes part; the file format wants a finite value
                           friction_ground=float(friction), friction_finger=float(friction),
                           effects=_truth_effects(effect_params)))


def _truth_effects(effect_params) -> list:
    """/truth effects (SPEC: [{"name": ..., parameter: value}], the simulator's parameter
    names) of ``effect_params``: the 3-D model's quasi-static soft ground as a plate of
    stiffness 1/compliance without damper."""
    from tacest.sim.effects import EFFECTS

    out = {}
    for k, v in (effect_params or {}).items():
        name, _, par = k.partition(".")
        if name not in EFFECTS:  # tacest's own extensions (edge_radius, ground_offset) are no SPEC effect
            continue
        if name == "soft_contact" and par == "compliance":
            par, v = "stiffness", 1.0 / float(v)
            out.setdefault(name, {"name": name, "damping": 0.0})
        out.setdefault(name, {"name": name})[par] = v
    return list(out.values())


def _vertices(shape: Shape3D, shape_params) -> np.ndarray:
    from tacest.geometry.shapes3d import numeric_vertices_3d

    return numeric_vertices_3d(shape, np.asarray(shape_params, float), 1.0)

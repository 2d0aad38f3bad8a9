"""``estimate_runs_3d(runs, shape, config)``: the implicit estimator for 3-D runs.

Pipeline (as in 2-D): scales → starting shape (from where the observed object rests) →
initial trajectory (the pose observations, or the prior's resting pose) → ground
impulses by non-negative least squares → staged solve (with fingers the contact
impulses alone, then the stages of ``[solver3d]``, IPOPT) → unscaled trajectories,
per-sample residuals, observed information → a :class:`tacest.io.estimate.Estimate`
with dim 3.  Without pose observations (finger pokes) the starts are push-tracked boxes
of a few extents and the resting box (initial3d.py), with restarts from the others when a
fit fails or violates its own physics, keeping the fit of lowest objective.
See docs/estimation3d.md.
A failed IPOPT solve raises SolveFailedError; nothing is reported as an estimate then.

Without a measured force (e.g. pose-only motion capture of a tossed object) the mass
is not identifiable: every impulse scales with it.  It is then held at the prior
(``identifiable["mass"] = False``, zero rows in the information matrix), and the inertia
is identified only relative to that mass (I / m).
"""

from __future__ import annotations

import json
import logging
import time

import casadi as ca
import numpy as np

from tacest.dynamics.rigid3d import (align_quaternion_signs, cholesky_from_inertia, inertia_numeric,
                                     quat_log_rate)
from tacest.errors import SolveFailedError, TacestError
from tacest.estimation.sensor_noise import judged_params, settings_for
from tacest.estimation.bounds import FRICTION_BOUNDS, INERTIA_DIAG_BOUNDS, INERTIA_OFFDIAG_BOUND, LOG_MASS_BOUNDS
from tacest.estimation.config import EstimatorConfig, solver_structure_key, start_workers
from tacest.estimation.data import (Scales, choose_scales, finger_start_positions, finger_velocity, force_in_contact,
                                   gravity_of, previous_trajectories, touch_ends, touching)
from tacest.estimation.initial3d import (Start3D, continued_track, iter_start_candidates_3d, push_tracker_3d,
                                         smoothed_start_track, touch_inconsistency_3d)
from tacest.estimation.smc import best_lineages
from tacest.estimation.smc3d import SMC3DSettings, smc_start_3d
from tacest.estimation.problem3d import Problem3D
from tacest.estimation.fitquality import goodness_of_fit
from tacest.estimation.result import (FitFacts, assemble, ended_at_bound, shape_params_at_bound, shape_seen,
                                      start_verdict)
from tacest.estimation.solver import (BuiltSolver, SolveOutcome, SolverCache, StageInfo, map_in_processes, pin,
                                      plan_stages, run_stages, solve_from_starts)
from tacest.estimation.uncertainty import observed_information_3d, vertex_jacobian
from tacest.geometry.shapes3d import Shape3D, make_shape_3d, numeric_vertices_3d
from tacest.geometry.transforms import quat_to_matrix
from tacest.io.estimate import Estimate, RunEstimate
from tacest.io.run import Run, run_sha256
from tacest.model.priors import prior_head
from tacest.model.stage2d import PHYSICS_TERMS
from tacest.model.registry import names_of, resolve
from tacest.model.stage3d import D_NAMES, DF_NAMES, DI, G3_NAMES, NP, PHYS_NAMES_3D, TERMS3D, Layout3D, impulse_variable

log = logging.getLogger(__name__)

#: Estimator3D.choose_start_shape: range of starting scales (units of L) and the
#: relative width of its histogram bins (0.5 %: 0.5 mm on a 10 cm object, finer than the
#: spread of a resting object's height under motion-capture noise but not much finer)
START_SCALE_RANGE = (0.2, 5.0)
START_SCALE_BIN = 0.005
#: factors on the mode tried by the refinement (0.5 % steps up to 6 %)
START_SCALE_REFINE = np.array([0.995, 1.0, 1.01, 1.02, 1.03, 1.045, 1.06])
#: largest number of fingers a 3-D run may have
MAX_FINGERS = 8

#: one structure at a time: a 3-D problem holds large CasADi graphs
_SOLVERS = SolverCache(limit=1)


def check_runs_3d(runs: list[Run]):
    """One clear error for runs the 3-D estimator cannot use."""
    if not runs:
        raise TacestError("no run files given")
    for r in runs:
        name = r.filename or "run"
        if r.dim != 3:
            raise TacestError(f"{name}: is {r.dim}-D; the 3-D estimator needs 3-D runs")
        if r.n_fingers and np.shape(r.finger_position)[-1] != 3 or (
                r.pose_obs is not None and np.shape(r.pose_obs)[-1] != 7):
            raise TacestError(f"{name}: not a valid 3-D run (fingertip positions need 3 coordinates, "
                              "poses 7)")
        if r.n_samples < 4:
            raise TacestError(f"{name}: needs at least 4 samples (3-D dynamics need three poses per interval)")
        if r.pose_obs is None and not r.n_fingers:
            raise TacestError(f"{name}: has neither pose observations nor fingertip data: nothing to estimate from")
        if r.pose_obs is not None and not np.any(np.all(np.isfinite(r.pose_obs), axis=1)):
            raise TacestError(f"{name}: /observations/pose has no observed (finite) row")
        if r.n_fingers > MAX_FINGERS:
            raise TacestError(f"{name}: {r.n_fingers} fingers; the 3-D estimator handles at most {MAX_FINGERS}")
        if not (r.sigma_position > 0 and r.sigma_angle > 0):
            raise TacestError(f"{name}: /observations/pose sigmas must be > 0")


def effects_3d(shape: Shape3D, config: EstimatorConfig, effects=()) -> tuple:
    """The effects a 3-D fit models, canonical order: ``edge_radius`` (boxes) and
    ``ground_offset`` where their prior sigmas in [solver3d] are above 0, and ``effects``
    (names of tacest.model.registry modelled in 3-D; docs/estimation3d.md, "Effects")."""
    s3 = config.solver3d
    for k in ("ground_offset_sigma", "edge_radius_sigma"):
        v = getattr(s3, k)
        if not (np.isfinite(v) and v >= 0):
            raise TacestError(f"solver3d.{k} must be >= 0, got {v!r}")
    out = []
    if s3.edge_radius_sigma > 0 and shape.name == "box":  # rounded edges are a box's effect only
        out.append("edge_radius")
    if s3.ground_offset_sigma > 0:
        out.append("ground_offset")
    return names_of(resolve(list(out) + [str(e) for e in (effects or ())], 3))


def solver_for_3d(shape: Shape3D, layout: Layout3D, config: EstimatorConfig, effects=()) -> BuiltSolver:
    """The cached solver of this structure (built on first use)."""
    import dataclasses

    # the effects' prior sigmas are NLP parameters, and how starts are compared and
    # stages stop is the solve's: not structure
    s3 = dataclasses.replace(config.solver3d, ground_offset_sigma=0.0, edge_radius_sigma=0.0, compare_starts=True,
                             acceptable_tol_no_pose=1.0)
    key = (shape.name, layout, solver_structure_key(config.solver), repr(s3), tuple(effects))
    return _SOLVERS.get(key, lambda: BuiltSolver(Problem3D(shape, layout, config, effects), config))


# ---------------------------------------------------------------------------------
# data


#: box_extents_from_poses: an extent counts as measured when the samples that touch the
#: ground hold this much of its direction along the vertical (Σ |u_i|, u the ground
#: normal in the body frame: five samples resting on a face perpendicular to it)
MEASURED_AXIS_WEIGHT = 5.0


def box_extents_from_poses(runs: list, L: float, cube: float) -> np.ndarray:
    """(3,) starting extents of a box (units of L) from its observed poses: wherever the
    box touches the ground (resting on a face, pivoting on an edge or a corner while it
    tips), its centre's height over the ground is its support along the ground normal,
    Σ_i (e_i / 2)·|u_i| with u = Rᵀ·up, linear in the extents e; samples in flight lie
    above that.  The lower envelope: non-negative least squares over the samples, then
    again over those within three position sigmas of the fit (the flights drop out),
    until the set settles.  A box that topples rests on two faces and shows two extents;
    an extent whose axis never points along the ground normal (MEASURED_AXIS_WEIGHT) is
    ``cube`` (the cube-like start's scale)."""
    from scipy.optimize import nnls

    U, h = [], []
    sigma = 1e-3
    for run in runs:
        poses, ok = observed_poses(run, smooth=True)
        if poses is None or not ok.any():
            continue
        up = np.asarray(run.up, float) / np.linalg.norm(run.up)
        R = quat_to_matrix(poses[ok, 3:])
        U.append(np.abs(np.einsum("tji,j->ti", R, up)))  # (T, 3): |Rᵀ up|
        h.append((poses[ok, :3] @ up - run.ground_height) / L)
        sigma = float(run.sigma_position) if getattr(run, "sigma_position", None) else sigma
    if not U:
        return np.full(3, cube)
    U, h = np.concatenate(U), np.concatenate(h)
    A = 0.5 * U
    sel = np.ones(len(h), bool)
    e = np.full(3, cube)
    for _ in range(20):
        if sel.sum() < 3:
            break
        e, _ = nnls(A[sel], h[sel])
        new = h - A @ e < 3.0 * sigma / L
        if np.array_equal(new, sel):
            break
        sel = new
    measured = U[sel].sum(axis=0) >= MEASURED_AXIS_WEIGHT
    return np.where(measured & (e > 0), e, cube)


def observed_poses(run: Run, smooth: bool = False):
    """(poses (T, 7) with missing rows filled by interpolation, observed (T,) bool), or
    (None, all False) without observations.  Quaternions are normalised and their signs
    made continuous; the filled rows are for the starts only.  ``smooth``: the track
    smoothed (:func:`smoothed_start_track`), for the starts (trajectory and shape), never
    for the pose residuals."""
    T = run.n_samples
    if run.pose_obs is None:
        return None, np.zeros(T, bool)
    P = np.array(run.pose_obs, float)
    ok = np.all(np.isfinite(P), axis=1)
    P[ok, 3:] /= np.linalg.norm(P[ok, 3:], axis=1, keepdims=True)
    P[:, 3:] = align_quaternion_signs(P[:, 3:])
    idx = np.nonzero(ok)[0]
    t = np.arange(T)
    filled = np.stack([np.interp(t, idx, P[idx, c]) for c in range(7)], 1)
    filled[:, 3:] /= np.linalg.norm(filled[:, 3:], axis=1, keepdims=True)
    return (smoothed_start_track(filled) if smooth else filled), ok


def data_matrix_3d(run: Run, F: int, scales: Scales) -> np.ndarray:
    """(n_data, T) per-sample data of one run in the layout of problem3d.D_NAMES /
    DF_NAMES (F fingers; a run with fewer is padded with zero weights)."""
    T = run.n_samples
    D = np.zeros((len(D_NAMES) + len(DF_NAMES) * F, T))
    grav = gravity_of(run)
    D[DI["dt"]] = run.dt
    D[DI["Lam"]] = scales.m0 * grav * run.dt
    D[DI["grav"]] = grav
    D[DI["gx"]: DI["gz"] + 1] = np.asarray(run.gravity, float)[:, None]
    D[DI["nx"]: DI["nz"] + 1] = np.asarray(run.up, float)[:, None]
    D[DI["h"]] = run.ground_height
    D[DI["sig_pos"]] = run.sigma_position
    D[DI["sig_ang"]] = run.sigma_angle
    D[DI["qw"]] = 1.0
    poses, ok = observed_poses(run)
    if poses is not None:
        D[DI["w_pose"]] = ok.astype(float)
        D[DI["px"]: DI["qz"] + 1] = np.where(ok[:, None], poses, D[DI["px"]: DI["qz"] + 1].T).T
    D[DI["w_rest"], 0] = 0.0 if ok[0] else 1.0  # a run that starts unobserved starts at rest
    if run.n_fingers:
        valid = ~run.finger_missing_mask  # (T, F)
        on = touching(run) & valid
        ends, start = touch_ends(run), finger_start_positions(run)
        vel = finger_velocity(run)
        for f in range(run.n_fingers):
            o = len(D_NAMES) + len(DF_NAMES) * f
            D[o: o + 3] = run.finger_position[:, f].T
            D[o + 3: o + 6] = vel[:, f].T
            D[o + 6] = on[:, f]
            D[o + 7: o + 10] = np.where(np.isfinite(run.normal[:, f]), run.normal[:, f], 0.0).T
            if run.force is not None:
                D[o + 10: o + 13] = run.force[:, f].T
                D[o + 13] = valid[:, f]
            D[o + 14] = valid[:, f]
            D[o + 15] = run.finger_radius[f]
            D[o + 16: o + 19] = start[:, f].T  # the interval's start
            D[o + 19] = ends[:, f]
    for f in range(run.n_fingers, F):  # padding: a finger far away with no weight
        D[len(D_NAMES) + len(DF_NAMES) * f + 15] = 1.0
    return D


def global_vector_3d(config: EstimatorConfig, scales: Scales, eps, comp_mult, dyn_mult=1.0) -> np.ndarray:
    """(len(G3_NAMES),) shared settings of the 3-D stage functions: the scales, the noise
    levels of ``config`` and one homotopy stage's (eps, comp_mult, dyn_mult)."""
    nz = config.noise
    gvals = dict(L=scales.L, m0=scales.m0, sig_proc=nz.process, sig_pen=nz.penetration, sig_gap=nz.contact_gap,
                 sig_comp=nz.complementarity, eps=eps, comp_mult=comp_mult, dyn_mult=dyn_mult,
                 sig_force=nz.force, sig_normal=nz.normal, sig_diss=nz.dissipation, sig_rest=nz.rest)
    return np.array([gvals[n] for n in G3_NAMES], float)


class Estimator3D:
    """Implicit estimator for a set of 3-D runs of one object."""

    #: one more start from an earlier estimate of the first samples of these runs
    #: (:func:`previous_start`), or None
    previous: Start3D | None = None

    def __init__(self, runs: list[Run], shape_spec: str = "box", config: EstimatorConfig | None = None,
                 fixed_theta=None, effects=(), accept_budget: bool = False, previous: Estimate | None = None):
        check_runs_3d(runs)
        self.accept_budget = bool(accept_budget)  # a fit may end on its iteration budget (solver.run_stages)
        #: (n_theta,) scaled parameters to hold (the trajectories alone are fitted: a
        #: held-out evaluation of a model), or None
        self.fixed_theta = None if fixed_theta is None else np.asarray(fixed_theta, float).copy()
        self.runs = runs
        #: the fit's settings (touch alone: the sensors' noise levels as the runs show
        #: them where larger) and the report of those levels (sensor_noise.py)
        self.config, self.sensor_noise = settings_for(runs, config or EstimatorConfig())
        self.shape = make_shape_3d(shape_spec)
        self.scales: Scales = choose_scales(runs, self.config)
        self.F = max(r.n_fingers for r in runs)
        self.layout = Layout3D(lengths=tuple(int(r.n_samples) for r in runs), F=self.F)
        self.has_force = force_in_contact(runs)  # a force measured in contact: the mass is told
        self.has_pose = any(r.pose_obs is not None for r in runs)
        size_bounds = [float(r.prior["size_bound"]) for r in runs if "size_bound" in r.prior]
        self.size_bound = min(size_bounds) if size_bounds else self.config.prior.size_bound
        if not self.size_bound > self.scales.L * MIN_BOUND_OVER_SCALE:
            raise TacestError(f"size bound {self.size_bound:g} m is below the length scale {self.scales.L:g} m "
                              f"times {MIN_BOUND_OVER_SCALE}: no shape fits")
        self.s0 = self.shape.initial(np.full(3, 1.0))  # a cube of the length scale
        self.previous = None if previous is None else previous_start(runs, self.shape, previous, self.scales.L)
        #: the modelled effects (effects_3d)
        self.effects = effects_3d(self.shape, self.config, effects)
        t0 = time.perf_counter()
        self.built = solver_for_3d(self.shape, self.layout, self.config, self.effects)
        self.build_time = time.perf_counter() - t0
        self.problem: Problem3D = self.built.problem
        self.z = None
        self.p_final = None
        #: per run the (T, 7) starting poses of the current start (initial3d.py), or None
        #: for :meth:`start_poses`
        self.start_tracks = None
        #: one dict per solve attempt (start, status, objective, physics per sample)
        self.attempts: list[dict] = []
        self.bounds_final = None

    # --------------------------------------------------------------------------------
    def params(self, eps, comp_mult, dyn_mult=1.0, ridge=None, s_ref=None):
        """Parameter vector p of the NLP."""
        cfg, sc = self.config, self.scales
        pr3 = self.problem
        D = np.concatenate([data_matrix_3d(r, self.F, sc) for r in self.runs], axis=1)
        g = global_vector_3d(cfg, sc, eps, comp_mult, dyn_mult)
        w = np.array([getattr(cfg.weights, t) for t in TERMS3D], float)
        prior = np.concatenate([prior_head(cfg.prior), pr3.effect_priors(cfg, sc.L), self.s0 if s_ref is None else s_ref])
        ridge = cfg.solver3d.hessian_ridge if ridge is None else ridge
        p = np.concatenate([D.T.reshape(-1), g, w, prior, [ridge]])
        assert p.shape[0] == self.problem.n_p
        return p

    def initial_guess(self, s0=None) -> np.ndarray:
        """Scaled z0: theta (shape s0, log mass 0, uniform-density inertia, friction at
        the prior, effect parameters at their start or prior centre), the observed (or
        resting) poses, small ground impulses (replaced by
        :meth:`ground_impulses_nnls` before the solve), finger impulses from the
        measured force (or a small push along the measured normal)."""
        pr, sc = self.problem, self.scales
        s0 = self.s0 if s0 is None else np.asarray(s0, float)
        theta = np.zeros(pr.n_theta)
        theta[: pr.n_shape] = s0
        theta[pr.n_shape + 1: pr.n_shape + 7] = np.array(
            ca.DM(self.shape.uniform_cholesky_reference(ca.DM(s0)))).reshape(-1)
        theta[pr.theta_index("friction_ground")] = self.config.prior.friction
        theta[pr.theta_index("friction_finger")] = self.config.prior.friction
        for j, (_, par) in enumerate(pr.effect_params):  # as the 2-D start (initial.py)
            theta[pr.n_shape + len(PHYS_NAMES_3D) + j] = par.centre if par.start is None else par.start
        X = np.zeros((NP, self.layout.S))
        LF = np.zeros((3 * self.F, self.layout.M))
        V = numeric_vertices_3d(self.shape, s0, sc.L)
        for i, run in enumerate(self.runs):
            poses = self.start_tracks[i] if self.start_tracks is not None else self.start_poses(run, V)
            X[:, self.layout.run_samples(i)] = np.concatenate([poses[:, :3] / sc.L, poses[:, 3:]], 1).T
            if run.n_fingers:
                T = run.n_samples
                Lam = sc.m0 * sc.g * run.dt
                on = touching(run)[2:]
                n = np.where(np.isfinite(run.normal[2:]), run.normal[2:], 0.0)
                imp = run.force[2:] * run.dt / Lam if run.force is not None else -0.3 * n
                imp = imp * on[:, :, None]  # (T-2, F, 3)
                blk = np.zeros((T - 2, 3 * self.F))
                blk[:, : 3 * run.n_fingers] = imp.reshape(T - 2, -1)
                LF[:, self.layout.run_intervals(i)] = blk.T
        U = impulse_variable(np.full((pr.K, self.layout.M), 1e-3))
        return pr.join(theta, X, U, LF)

    def start_poses(self, run: Run, V_body: np.ndarray) -> np.ndarray:
        """(T, 7) starting poses: the observations (:func:`observed_poses`: interpolated
        where missing, smoothed), else the prior's initial pose, else resting on the ground
        at the origin, unrotated."""
        poses, ok = observed_poses(run, smooth=True)
        if poses is not None:
            return poses
        if "initial_pose" in run.prior:
            pose0 = np.asarray(run.prior["initial_pose"], float)[:7].copy()
            pose0[3:] /= np.linalg.norm(pose0[3:])
        else:
            pose0 = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
            up = np.asarray(run.up, float)
            lowest = np.min((V_body @ quat_to_matrix(pose0[3:]).T) @ up)
            pose0[:3] = (run.ground_height - lowest) * up
        return np.repeat(pose0[None], run.n_samples, 0)

    def variable_bounds(self, z):
        """lbx, ubx (scaled): shape and parameter bounds; finger impulses 0 where the
        fingertip did not touch; the mass fixed without a force stream; the gauge."""
        pr = self.problem
        lbx = np.full(pr.n_z, -np.inf)
        ubx = np.full(pr.n_z, np.inf)
        ns = pr.n_shape
        lbx[:ns], ubx[:ns] = self.shape.bounds(self.size_bound / self.scales.L)
        i_lm = pr.theta_index("log_mass")
        lbx[i_lm], ubx[i_lm] = LOG_MASS_BOUNDS
        if not self.has_force:  # mass is not identifiable without a force measured in contact
            pin(lbx, ubx, [i_lm], [0.0])
        for k, name in enumerate(PHYS_NAMES_3D[1:7]):
            j = pr.theta_index(name)
            lbx[j], ubx[j] = INERTIA_DIAG_BOUNDS if k < 3 else (-INERTIA_OFFDIAG_BOUND, INERTIA_OFFDIAG_BOUND)
        for name in ("friction_ground", "friction_finger"):
            j = pr.theta_index(name)
            lbx[j], ubx[j] = FRICTION_BOUNDS
        a = pr.n_shape + len(PHYS_NAMES_3D)  # the effects' parameters
        for j, (e, par) in enumerate(pr.effect_params):
            lbx[a + j], ubx[a + j] = e.bounds(par, self.config, self.scales.L, lbx[:ns])
        if not self.F:  # no fingertip: its friction is not in the model; hold it at the prior
            j = pr.theta_index("friction_finger")
            pin(lbx, ubx, [j], [z[j]])
        if self.fixed_theta is not None:
            pin(lbx, ubx, np.arange(pr.n_theta), self.fixed_theta)
        if self.F:
            for i, run in enumerate(self.runs):
                on = np.zeros((run.n_samples - 2, self.F), bool)
                if run.n_fingers:
                    on[:, : run.n_fingers] = touching(run)[2:]
                idx = pr.lf_index(np.arange(self.layout.M)[self.layout.run_intervals(i)])  # (T-2, 3F)
                off = np.repeat(~on, 3, axis=1)
                lbx[idx[off]] = 0.0
                ubx[idx[off]] = 0.0
        if self.shape.name != "box" and not self.has_pose:
            # gauge: a free polytope can rotate in its body frame; fix run 0's start orientation
            j = pr.x_index([0])[0, 3:7]
            lbx[j] = ubx[j] = z[j]
        return lbx, ubx

    def choose_start_shape(self):
        """Starting shape parameters: the cube-like ``initial(c·(1, 1, 1))`` scaled to touch
        the ground where the observed object most often does.  For every observed pose,
        the scale c_t at which the lowest vertex of the unit-scale shape would touch the
        ground is (COM height) / (support distance downward); samples at rest or sliding
        pile up at one value, samples in flight spread above it.  c is the mode of the c_t
        (a histogram of START_SCALE_BIN relative width).  Without pose observations the
        start is the shape of size L."""
        if not self.has_pose:
            return self.s0
        V = numeric_vertices_3d(self.shape, self.shape.initial(np.ones(3)), self.scales.L) / self.scales.L
        scales = []
        for run in self.runs:
            poses, ok = observed_poses(run, smooth=True)
            if poses is None or not ok.any():
                continue
            up = np.asarray(run.up, float)
            R = quat_to_matrix(poses[ok, 3:])
            support = np.max(-np.einsum("tij,kj->tki", R, V) @ up, axis=1)  # (T,) in units of L
            height = (poses[ok, :3] @ up - run.ground_height) / self.scales.L
            c = height[support > 0] / support[support > 0]
            scales.append(c[(c > START_SCALE_RANGE[0]) & (c < START_SCALE_RANGE[1])])
        c = np.concatenate(scales) if scales else np.zeros(0)
        if c.size < 10:
            return self.s0
        edges = np.exp(np.arange(np.log(START_SCALE_RANGE[0]), np.log(START_SCALE_RANGE[1]), START_SCALE_BIN))
        hist, _ = np.histogram(c, edges)
        hist = np.convolve(hist, np.ones(3), mode="same")  # a cluster split by a bin edge still wins
        k = int(np.argmax(hist))
        mode = float(np.median(c[(c >= edges[max(k - 1, 0)]) & (c < edges[min(k + 2, len(edges) - 1)])]))
        base = np.full(3, mode)
        if self.shape.name == "box":
            base = box_extents_from_poses(self.runs, self.scales.L, mode)
        # the mode is biased low: orientation noise tilts the observed resting object, and
        # a tilted shape reaches lower; refine on a grid above it by the loss after
        # non-negative least squares impulses (too small: impulses act at a distance;
        # too large: penetration)
        p = self.params(*self.config.solver3d.homotopy[-1])
        candidates = [base * f for f in START_SCALE_REFINE]
        losses = [self.nnls_loss(self.initial_guess(self.shape.initial(c_)), p) for c_ in candidates]
        return self.shape.initial(candidates[int(np.argmin(losses))])

    def nnls_loss(self, z, p) -> float:
        """The loss 0.5 |r|² of the dynamic intervals after :meth:`ground_impulses_nnls`."""
        return float(self.ground_impulses_nnls(z, p, return_loss=True))

    def ground_impulses_nnls(self, z, p, return_loss=False):
        """z with the ground impulses replaced by the solution of the impulses-only
        problem for the current poses, shape and parameters: with those held, every
        residual is affine in the interval's impulses lambda_n (K,) (the dynamics, the
        closed-form friction and the complementarity are linear in them), so the problem
        splits into one K-variable non-negative least squares per interval.  (With
        soft_contact the gaps depend on the load, and the linearization at lambda_n = 0
        is only a start.)"""
        from scipy.optimize import nnls

        pr = self.problem
        theta, X, U, LF = pr.split(z)
        D, g, w = pr.split_parameters(p)
        M = self.layout.M
        poses, D_win = pr.stage_window_arguments(X, D)
        args = poses + [np.zeros_like(U), LF, theta, D_win, g, w]
        res, jac = pr.direct_residual_functions()
        r0 = np.asarray(res.map(M)(*args))  # (n_r, M) at lambda_n = 0
        A = np.asarray(jac.map(M)(*args))  # (n_r, K M)
        K = pr.K
        LN = np.zeros_like(U)
        loss = 0.0
        for n in range(M):
            LN[:, n], rn = nnls(A[:, K * n: K * (n + 1)], -r0[:, n])
            loss += 0.5 * rn * rn
        if return_loss:
            return loss
        return pr.join(theta, X, impulse_variable(LN), LF)

    def _impulse_only(self, lbx, ubx, z):
        pr = self.problem
        free = np.zeros(pr.n_z, bool)
        free[pr.u_offset:] = True
        return np.where(free, lbx, z), np.where(free, ubx, z)

    # --------------------------------------------------------------------------------
    def solve(self) -> SolveOutcome:
        """Staged solves (:meth:`solve_from_shape`).  Runs with pose observations (or held
        parameters, or no fingertip) solve once, from the observed poses and
        :meth:`choose_start_shape` (with an effect that models impacts, twice:
        :func:`solve_observed_tracks`).  Without pose observations: the starts of
        :func:`order_starts` (initial3d.iter_start_candidates_3d's and
        :meth:`sampled_starts`), the compared ones all solved, then restarts (the further
        push-tracked starts are searched for only then) while the fit of lowest objective
        fails or violates its own physics by more than ``solver3d.restart_physics``
        (solver.solve_from_starts: a fit that used up its budget competes by objective).
        Held parameters, runs poked unseen: one solve from :func:`held_shape_tracks`."""
        pr, cfg3 = self.problem, self.config.solver3d
        self.attempts = []
        if self.has_pose or self.fixed_theta is not None or not self.F:
            if self.previous is not None:
                log.warning("the earlier estimate is not used: runs with pose observations (or held parameters, "
                            "or no fingertip) are solved once, from their own start")
            t0 = time.perf_counter()
            s0 = self.choose_start_shape() if self.fixed_theta is None else self.fixed_theta[: pr.n_shape].copy()
            log.info(f"starting shape {np.round(s0 * self.scales.L, 4)} m ({time.perf_counter() - t0:.2f} s)")
            held = self.fixed_theta is not None and self.F and any(r.pose_obs is None for r in self.runs)
            if not held and self.has_pose and pr.n_poses > 3:
                return solve_observed_tracks(self, s0)
            self.start_tracks = held_shape_tracks(self.runs, self.shape, s0, self.scales.L) if held else None
            try:
                return self.solve_from_shape(s0)
            finally:
                self.start_tracks = None
        t0 = time.perf_counter()
        found = iter_start_candidates_3d(self.runs, self.scales.L, np.ones(3), 1 + int(cfg3.restarts))
        starts = first_starts(found, int(cfg3.compared_push_tracked) if cfg3.compare_starts else 1)
        starts, compared = order_starts(starts, self.sampled_starts(starts[0]), cfg3)
        if self.previous is not None:  # first, and compared (as in 2-D)
            starts.insert(0, self.previous)
            compared += 1
        L = self.scales.L
        log.info(f"{len(starts)} starts ({time.perf_counter() - t0:.2f} s): " + starts_text(starts, L))

        def solve_one(c, abandon_above):
            s0 = self.shape.initial(c.extents) if c.shape_params is None else c.shape_params
            return solve_start(self, s0, c.poses, abandon_above)

        try:
            out, (self.s0, self.p_final, self.bounds_final) = solve_from_starts(
                [(start_record(c, L), c) for c in starts], solve_one, cfg3.restart_physics, self.attempts,
                min_solves=compared, accept_budget=self.accept_budget, workers=start_workers(self.config.solver),
                abandon=self.config.solver.abandon_hopeless, more=later_starts(found, cfg3.compare_starts, L))
        except SolveFailedError as first:  # every start was solved (the later ones too): one attempt each
            if len(self.attempts) == 1:
                raise
            raise SolveFailedError(f"no converged fit from any of {len(self.attempts)} starts; "
                                   f"the first: {first}") from None
        self.z = out.z
        return out

    def sampled_starts(self, tracked: Start3D) -> list:
        """The sampler's starts (:func:`sampled_starts_3d`), [] where it is off.  Its
        hypotheses are boxes: another shape starts as its ``initial`` of a lineage's
        extents, on the lineage's poses."""
        if not self.config.solver3d.sampler_particles:
            return []
        return sampled_starts_3d(self.runs, self.scales, tracked, self.config)

    def fit_quality(self, z):
        """The goodness-of-fit test of the fit at z (fitquality.goodness_of_fit)."""
        return goodness_of_fit([res for *_, res in self.run_results(z)], self.runs, self.problem.K,
                               weights=self.config.to_dict().get("weights", {}))

    def physics_per_sample(self, z) -> float:
        """Objective units per sample of the physics terms (stage2d.PHYSICS_TERMS: dynamics,
        penetration, complementarity, dissipation, cone; weights applied) at z with the
        final stage's parameters: how far a fit violates its own model."""
        _, _, w = self.problem.split_parameters(self.p_final)
        st, o0 = self.stage_outputs(z)
        total = 0.0
        for t in PHYSICS_TERMS:
            wt = float(w[TERMS3D.index(t)])
            total += wt * 0.5 * float(np.sum(st[t] ** 2)) if st[t].size else 0.0
            if t in o0 and o0[t].size:
                total += wt * 0.5 * float(np.sum(o0[t] ** 2))
        return total / self.layout.S

    def stages(self):
        """The stage plan (solver.plan_stages): runs without pose observations have stages
        of their own (the pose-observed path keeps [solver3d] homotopy, hessian and
        acceptable_tol); an impulses stage only where fingers push."""
        cfg, cfg3 = self.config.solver, self.config.solver3d
        hom = cfg3.homotopy if self.has_pose else cfg3.homotopy_no_pose
        hessian = cfg3.hessian if self.has_pose else cfg3.hessian_no_pose
        max_iter = cfg.max_iter if self.has_pose else cfg3.max_iter_no_pose
        return plan_stages(hom, hessian, max_iter, cfg.stage_max_iter, impulses_first=bool(self.F),
                           acceptable_tol=None if self.has_pose else cfg3.acceptable_tol_no_pose)

    def stage_bounds(self, stage, z):
        lbx, ubx = self.variable_bounds(z)
        if not stage.impulses_only:
            return lbx, ubx
        free = np.zeros(self.problem.n_z, bool)
        free[self.problem.u_offset:] = True
        return np.where(free, lbx, z), np.where(free, ubx, z)

    def stage_params(self, stage, retry=False):
        ridge = max(self.config.solver3d.hessian_ridge, 1.0) if retry else None
        return self.params(stage.eps, stage.comp_mult, stage.dyn_mult, ridge=ridge)

    def solve_from_shape(self, s0, accept_budget=None, abandon_above=float("inf")) -> SolveOutcome:
        """One staged solve from the starting shape s0 (scaled): the ground impulses by
        non-negative least squares for the observed (or starting) trajectory, then the
        stages of :meth:`stages` (solver.run_stages; ``accept_budget``, by default the
        estimator's: a final stage that uses up its budget keeps its last iterate and
        status, success False; ``abandon_above``: the best fit's objective so far, far
        above which the final stage stops, StartAbandoned)."""
        pr = self.problem
        self.s0 = np.asarray(s0, float)
        z = self.initial_guess()
        if self.fixed_theta is not None:
            z[: pr.n_theta] = self.fixed_theta
        stages = self.stages()
        t0 = time.perf_counter()
        z = self.ground_impulses_nnls(z, self.stage_params(stages[0]))
        nnls_time = time.perf_counter() - t0
        log.info(f"ground impulses by non-negative least squares: {nnls_time:.2f} s")
        out = run_stages(self.built, z, stages, self.stage_params, self.stage_bounds,
                         accept_budget=self.accept_budget if accept_budget is None else accept_budget,
                         abandon_above=abandon_above)
        out.stages.insert(0, StageInfo(name="ground impulses (nnls)", status="Solve_Succeeded", iterations=0,
                                       wall_time=nnls_time, objective=float("nan")))
        out.wall_time += nnls_time
        self.z = out.z
        self.p_final = self.stage_params(stages[-1])
        self.bounds_final = self.variable_bounds(self.z)
        return out

    # --------------------------------------------------------------------------------
    def effect_params(self, z) -> dict:
        """{estimate /params name: physical value} of the effects' parameters at z
        (edge_radius, ground_offset in m)."""
        pr = self.problem
        th = np.asarray(z, float)[: pr.n_theta]
        u = pr.effect_values(th)
        mu_g = float(th[pr.theta_index("friction_ground")])
        out = {}
        for e in pr.effect_objects:
            out.update(e.report(u[e.name], self.scales, pr.K, mu_g))
        return out

    def com_offset(self, z) -> np.ndarray:
        """(3,) m: the estimated centre of mass in the shape's frame (zeros when not
        estimated)."""
        p = self.effect_params(z)
        return np.array([float(p.get(f"com_offset.d{a}", 0.0)) for a in "xyz"])

    def body_vertices(self, z) -> np.ndarray:
        """(K, 3) m: the estimated vertices in the body frame (origin at the centre of
        mass)."""
        th = np.asarray(z, float)[: self.problem.n_theta]
        return numeric_vertices_3d(self.shape, th[: self.problem.n_shape], self.scales.L) - self.com_offset(z)

    def physical(self, z):
        """(vertices (K, 3) m, mass kg, inertia (3, 3) kg·m², mu_g, mu_f)."""
        pr, sc = self.problem, self.scales
        th = np.asarray(z, float)[: pr.n_theta]
        mass = sc.m0 * float(np.exp(th[pr.theta_index("log_mass")]))
        inertia = mass * sc.L ** 2 * inertia_numeric(th[pr.n_shape + 1: pr.n_shape + 7])
        return (self.body_vertices(z), mass, inertia,
                float(th[pr.theta_index("friction_ground")]), float(th[pr.theta_index("friction_finger")]))

    def stage_outputs(self, z, p=None):
        """({name: (n_out, M)} stage outputs over all dynamic intervals, {name: (n_out, R)}
        start outputs over the runs)."""
        pr = self.problem
        theta, X, U, LF = pr.split(z)
        D, g, _ = pr.split_parameters(self.p_final if p is None else p)
        poses, D_win = pr.stage_window_arguments(X, D)
        out = pr.stage_fun.map(self.layout.M)(*poses, U, LF, theta, D_win, g)
        f0 = pr.first
        o0 = pr.start_fun.map(len(self.runs))(X[:, f0], X[:, f0 + 1], theta, D[:, f0], D[:, f0 + 1], g)
        return ({n: np.asarray(v) for n, v in zip(pr.stage_fun.name_out(), out)},
                {n: np.asarray(v) for n, v in zip(pr.start_fun.name_out(), o0)})

    def run_results(self, z):
        """Per run: (pose (T, 7), velocity (T, 6) [v world m/s, omega world rad/s],
        impulses {name: N·s}, residuals {term: (T,)} (0.5 |r|² per sample, weights not
        applied)).  The velocity at sample t is that of the interval (t-1, t]; sample 0
        repeats sample 1's."""
        pr, sc = self.problem, self.scales
        _, X, _, _ = pr.split(z)
        st, o0 = self.stage_outputs(z)
        K = pr.K
        results = []
        for i, run in enumerate(self.runs):
            T = run.n_samples
            xs = X[:, self.layout.run_samples(i)].T
            iv = self.layout.run_intervals(i)
            q = xs[:, 3:7] / np.linalg.norm(xs[:, 3:7], axis=1, keepdims=True)
            pose = np.concatenate([xs[:, 0:3] * sc.L, q], 1)
            vel_b = np.zeros((T, 6))
            vel_b[2:] = st["velocity"][:, iv].T
            vel_b[1, :3] = (pose[1, :3] - pose[0, :3]) / run.dt
            vel_b[1, 3:] = quat_log_rate(q[0], q[1], run.dt)
            vel_b[0] = vel_b[1]
            w_world = np.einsum("tij,tj->ti", quat_to_matrix(q), vel_b[:, 3:])
            vel = np.concatenate([vel_b[:, :3], w_world], 1)
            Lam = sc.m0 * sc.g * run.dt
            lt = st["lam_t_ground"][:, iv].T.reshape(T - 2, K, 3)
            imp = {"ground_normal": np.vstack([np.zeros((2, K)), st["lam_n_ground"][:, iv].T * Lam]),
                   "ground_tangent": np.concatenate([np.zeros((2, K, 3)), lt * Lam], 0)}
            fi = st["imp_finger"][:, iv].T if self.F else np.zeros((T - 2, 0))
            for f in range(run.n_fingers):
                imp[f"finger_{f}"] = np.vstack([np.zeros((2, 3)), fi[:, 3 * f: 3 * f + 3]])
            res = {}
            for t in TERMS3D:
                vals = 0.5 * np.sum(st[t][:, iv] ** 2, axis=0) if st[t].size else np.zeros(T - 2)
                first = np.zeros(2)
                if t in o0 and o0[t].size:
                    blk = o0[t][:, i]
                    if t == "dynamics":  # the rest term belongs to sample 1
                        first[1] = 0.5 * float(np.sum(blk ** 2))
                    else:  # samples 0 and 1 stacked in equal halves
                        h = blk.size // 2
                        first = np.array([0.5 * np.sum(blk[:h] ** 2), 0.5 * np.sum(blk[h:] ** 2)])
                res[t] = np.concatenate([first, vals])
            results.append((pose, vel, imp, res))
        return results


    def result(self, out: SolveOutcome, wall_time: float, information=True) -> Estimate:
        """The Estimate of the fit ``out`` (result.assemble, the one policy of 2-D and 3-D)."""
        pr, sc = self.problem, self.scales
        V, mass, inertia, mu_g, mu_f = self.physical(out.z)
        run_ests = []
        for run, (pose, vel, imp, res) in zip(self.runs, self.run_results(out.z)):
            src = run.filename or ""
            run_ests.append(RunEstimate(pose=pose, velocity=vel, impulses=imp, residuals=res, source_file=src,
                                        source_sha256=run_sha256(run)))
        params = {"mass": mass, "inertia": inertia, "friction_ground": mu_g, "friction_finger": mu_f}
        params.update(self.effect_params(out.z))
        info = (observed_information_3d(pr, out.z, judged_params(self), *self.bounds_final, sc, mass)
                if information else None)
        th = np.asarray(out.z, float)
        a = pr.n_shape + len(PHYS_NAMES_3D)
        effect_sigma = {}
        for j, (e, par) in enumerate(pr.effect_params):
            _, sigma = e.prior(par, self.config, sc.L)
            effect_sigma[e.info_name(par)] = float(sigma) / e.info_factor(par, float(th[a + j]), sc)
        facts = FitFacts(has_force=self.has_force, has_fingers=self.F > 0,
                         at_bound={"mass": ended_at_bound(np.log(mass / sc.m0), LOG_MASS_BOUNDS),
                                   "friction_ground": ended_at_bound(mu_g, FRICTION_BOUNDS),
                                   "friction_finger": ended_at_bound(mu_f, FRICTION_BOUNDS)},
                         effect_sigma=effect_sigma, effects=pr.effects, held=self.fixed_theta is not None,
                         shape_seen=shape_seen(self.runs), shape_names=tuple(self.shape.param_names),
                         shape_at_bound=shape_params_at_bound(self.shape, th[: pr.n_shape],
                                                              self.size_bound / sc.L))
        notes = []
        if not self.has_force:
            notes.append("no force measured in contact: mass is not identifiable (held at the prior "
                         f"{sc.m0:g} kg); inertia is identified only relative to it (I/m)")
        return assemble(3, self.shape.name, V, params, run_ests, out, wall_time, info, facts, self.config.to_dict(),
                        "implicit", extra={"length_scale": sc.L, "mass_scale": sc.m0,
                                           "shape_params": np.asarray(out.z[: pr.n_shape] * sc.L, float)},
                        attempts=self.attempts, notes=notes, data=self.runs, sensor_noise=self.sensor_noise,
                        vertex_jacobian=vertex_jacobian(lambda p_: numeric_vertices_3d(self.shape, p_ / sc.L, sc.L),
                                                        np.asarray(out.z[: pr.n_shape], float) * sc.L))


#: the size bound must exceed this multiple of the length scale (the smallest extent is
#: MIN_SIZE_FRACTION of the bound; a bound below half the scale leaves no room to start)
MIN_BOUND_OVER_SCALE = 0.5



def sampled_starts_3d(runs: list, sc: Scales, tracked: Start3D, config: EstimatorConfig) -> list:
    """The sampler's starts (smc3d.py): of ``solver3d.sampler_runs`` runs of
    ``sampler_particles`` hypotheses (seeds sampler_seed, +1, ...; in forked processes:
    solver.map_in_processes; half of each run's hypotheses around the box of the
    ``tracked`` start), the lineages of the ``sampler_starts`` highest likelihoods
    (smc.best_lineages)."""
    cfg3 = config.solver3d
    found = map_in_processes(lambda k: smc_start_3d(runs, sc.L, sc.m0, tracked.extents * sc.L, SMC3DSettings(
        particles=int(cfg3.sampler_particles), seed=int(cfg3.sampler_seed) + k)), int(cfg3.sampler_runs),
        start_workers(config.solver))  # independent runs, seeded
    kept = best_lineages(found, int(cfg3.sampler_starts))
    out = []
    for best in kept:
        cost = sum(float(touch_inconsistency_3d(run, best.extents[None], P[None])[0]) for run, P in zip(runs, best.poses))
        out.append(Start3D(best.extents / sc.L, best.poses, "sampler", cost,
                           extra={"sampler_seed": best.seed, "log_likelihood": best.log_likelihood,
                                  "max_tilt_deg": best.max_tilt_deg}))
    return out


def solve_start(est: "Estimator3D", s0, tracks, abandon_above):
    """One start of solver.solve_from_starts: the staged solve from shape s0 (scaled)
    and the per-run start poses ``tracks`` (None: the estimator's own, start_poses)."""
    est.start_tracks = tracks
    try:  # solve_from_starts judges budget fits
        out = est.solve_from_shape(s0, accept_budget=True, abandon_above=abandon_above)
    finally:
        est.start_tracks = None
    return start_verdict(est, out, (s0, est.p_final, est.bounds_final))


def solve_observed_tracks(est: "Estimator3D", s0) -> SolveOutcome:
    """The pose-observed solve of a model with impacts (an effect whose stage looks
    back, restitution): from the smoothed observations (Estimator3D.start_poses) and from the
    observations themselves, both solved, the lower objective kept (attempts in
    ``starts``).  Why both: the smoothing that keeps observation noise out of the
    start's dynamics (initial3d.smoothed_start_track) rounds a bounce off over its
    window; from it a fit of bouncing tosses kept e at 0 (objective 1318 and 3892 on
    two noisy own-model recordings with e 0.6), from the observations it found e
    (e 0.45 ± 0.03 at objective 440 on the flat drop; docs/estimation3d.md,
    "Restitution")."""
    V = numeric_vertices_3d(est.shape, s0, est.scales.L)
    raw = []
    for run in est.runs:
        poses, _ = observed_poses(run, smooth=False)
        raw.append(poses if poses is not None else est.start_poses(run, V))
    starts = [({"start": "smoothed observations"}, None), ({"start": "observations"}, raw)]
    out, (est.s0, est.p_final, est.bounds_final) = solve_from_starts(
        starts, lambda tracks, abandon_above: solve_start(est, s0, tracks, abandon_above),
        est.config.solver3d.restart_physics, est.attempts, min_solves=len(starts),
        accept_budget=est.accept_budget, workers=start_workers(est.config.solver),
        abandon=est.config.solver.abandon_hopeless)
    est.z = out.z
    return out


def solve_warm(est: "Estimator3D", z_other, s0) -> SolveOutcome:
    """One solve of ``est``'s final stage from the solution ``z_other`` (scaled) of another
    fit of runs of the same lengths and fingers: the model ``est`` without its effects
    (whose theta are the first entries of est's; the effects start at their starting
    values, ``EffectParameter.start``), or the same model of slightly other data (a data
    transform's runs).  s0 : that fit's starting shape (the shape prior's reference, so
    that both objectives agree there).  Where every effect starts at its nested value
    (the plain model: all but restitution, whose e starts at 0.5 and whose impact relief
    holds at any e) the fit ends at or below the plain optimum's objective (up to the
    interior point's step inside the effects' bounds); restitution starts elsewhere and
    carries no such guarantee."""
    pr = est.problem
    z_other = np.asarray(z_other, float)
    n_plain = len(z_other) - (pr.n_z - pr.n_theta)
    if not 0 < n_plain <= pr.n_theta:
        raise TacestError(f"a solution of {len(z_other)} variables does not fit a problem of {pr.n_z}")
    est.s0 = np.asarray(s0, float)
    z = est.initial_guess()
    z[:n_plain] = z_other[:n_plain]
    z[pr.n_theta:] = z_other[n_plain:]
    if est.fixed_theta is not None:
        z[: pr.n_theta] = est.fixed_theta
    stages = est.stages()[-1:]
    out = run_stages(est.built, z, stages, est.stage_params, est.stage_bounds, accept_budget=est.accept_budget)
    est.z = out.z
    est.p_final = est.stage_params(stages[-1])
    est.bounds_final = est.variable_bounds(est.z)
    return out


def start_record(c: Start3D, L: float) -> dict:
    """The attempt record of start c (solver.solve_from_starts): its label, extents (m;
    c's are in units of the length scale L m), touch inconsistency and what its maker
    noted (``extra``)."""
    return {"start": c.label, "start_extents": np.asarray(c.extents * L, float),
            "touch_inconsistency": float(c.inconsistency), **c.extra}


def starts_text(starts: list, L: float) -> str:
    """The starts' labels and extents (m), for the log."""
    return "; ".join(f"{c.label} {np.round(c.extents * L, 3)} m" for c in starts)


def later_starts(found, compare_starts: bool, L: float):
    """solver.solve_from_starts' ``more``: the rest of the iterator ``found``
    (initial3d.iter_start_candidates_3d), searched for once a restart is wanted, as
    (record, start) pairs; with ``compare_starts`` the resting one last
    (:func:`order_starts`)."""
    def later():
        t0 = time.perf_counter()
        more = list(found)
        if compare_starts:
            more = resting_last(more)
        log.info(f"{len(more)} more starts ({time.perf_counter() - t0:.2f} s): " + starts_text(more, L))
        return [(start_record(c, L), c) for c in more]

    return later


def first_starts(found, n_pushed: int) -> list:
    """The starts wanted before any solve, from the iterator ``found``
    (initial3d.iter_start_candidates_3d): up to its ``n_pushed``-th push-tracked one (at
    least its first start); all of them where the resting start comes among those (its
    place among the restarts depends on the later ones: :func:`order_starts`)."""
    first = []
    for c in found:
        first.append(c)
        if sum(s.poses is not None for s in first) >= max(1, n_pushed):
            break
    if any(c.poses is None for c in first):
        first += list(found)
    return first


def resting_last(starts: list) -> list:
    """The starts with a trajectory (push-tracked, sampled, an earlier estimate's) in
    their order, then those without (the resting start)."""
    return [c for c in starts if c.poses is not None] + [c for c in starts if c.poses is None]


def order_starts(starts: list, sampled: list, cfg3) -> tuple:
    """(starts in the order they are solved, how many are compared) from the push-tracked
    and resting starts (initial3d.start_candidates_3d) and the sampler's (smc.best_lineages): a
    lineage that tips by more than ``cfg3.sampler_tip_deg`` goes first (the push tracker
    never tips the box), a flat one after the first push-tracked start; with
    ``cfg3.compare_starts`` the sampler's starts and the best
    ``cfg3.compared_push_tracked`` push-tracked ones are compared, the further
    push-tracked ones are restarts, and the resting one goes last, a restart only
    (compared, it was far worse on all but one benchmark recording and crept to the
    iteration budget on two, 190 s)."""
    starts = list(starts)
    tipping = [c for c in sampled if c.extra["max_tilt_deg"] > cfg3.sampler_tip_deg]
    flat = [c for c in sampled if c.extra["max_tilt_deg"] <= cfg3.sampler_tip_deg]
    starts = tipping + starts[:1] + flat + starts[1:]
    if not cfg3.compare_starts:
        return starts, 0
    starts = resting_last(starts)
    pushed = sum(c.poses is not None for c in starts) - len(sampled)
    return starts, len(sampled) + min(pushed, int(cfg3.compared_push_tracked))


def previous_start(runs: list, shape: Shape3D, previous: Estimate, L: float) -> Start3D:
    """A start from an earlier estimate ``previous`` of the same object from the first
    samples of the same runs (a closed loop's last step, before its newest poke): its
    shape (Shape3D.params_from_vertices, scaled by the length scale L m) and its
    trajectories, each continued over the run's newer samples by the push tracker from
    its last pose (initial3d.continued_track).  Raises TacestError where the estimate
    does not fit the runs (data.previous_trajectories)."""
    before = previous_trajectories(previous, 3, shape.name, runs)
    # the vertices in the shape's own frame: an estimated centre of mass moved them by -d
    d = np.array([float(previous.params.get(f"com_offset.d{a}", 0.0)) for a in "xyz"])
    V = np.asarray(previous.vertices, float) + d
    s0 = shape.params_from_vertices(V, L)
    extents = np.ptp(V, axis=0) / L
    poses = [continued_track(run, extents * L, P) for run, P in zip(runs, before)]
    cost = sum(float(touch_inconsistency_3d(run, extents[None] * L, P[None])[0]) for run, P in zip(runs, poses))
    return Start3D(extents, poses, "previous estimate", cost, shape_params=s0)


def held_shape_tracks(runs, shape: Shape3D, s0, L: float) -> list:
    """Starting poses (T, 7) per run for a fit whose shape is held at s0 (scaled, length
    scale L m): the observed poses where a run has them, else the push tracker's box of
    the shape's extents (initial3d.push_tracker_3d: it slides and turns the box out of
    the touching fingertips' way), instead of the object resting where it started."""
    extents = np.ptp(numeric_vertices_3d(shape, s0, L), axis=0)
    out = []
    for run in runs:
        poses = observed_poses(run, smooth=True)[0]  # None without observations
        out.append(poses if poses is not None else push_tracker_3d(run, extents[None])[0])
    return out

def estimate_3d(runs: list[Run], shape_spec: str = "box", config: EstimatorConfig | None = None,
                effects=(), previous: Estimate | None = None) -> Estimate:
    """Estimate one object's shape, inertia, friction and every run's trajectory from 3-D
    runs; ``effects``: effect names modelled as extra parameters (tacest.model.registry,
    3-D); ``previous``: an earlier estimate of the first samples of the same runs, one
    more start where the runs have no pose observations (:func:`previous_start`).  See
    the module docstring."""
    t_start = time.perf_counter()
    config = config or EstimatorConfig()
    horizon = []
    if previous is None and config.solver3d.growing_horizon:
        previous, horizon = grow_horizon(runs, shape_spec, config, effects)
    est = Estimator3D(runs, shape_spec, config, effects=effects, previous=previous)
    pr = est.problem
    log.info(f"built 3-D NLP: {pr.n_z} variables, {pr.g.shape[0]} constraints ({est.build_time:.1f} s)")
    out = est.solve()
    result = est.result(out, time.perf_counter() - t_start)
    if horizon:
        result.extra_attrs["horizon"] = json.dumps(horizon)
    return result


def grow_horizon(runs: list[Run], shape_spec: str, config: EstimatorConfig, effects=()) -> tuple:
    """(the estimate of all but the last action, or None; the steps [{samples, status,
    objective, wall_time}]): the growing horizon of ``solver3d.growing_horizon``.  It
    applies to one run of at least two actions (tacest.io.slicing.action_ranges),
    without pose observations, with a fingertip; elsewhere it returns (None, []).  Step k
    estimates the run's samples up to the end of action k, started from step k-1's
    estimate too (Estimator3D's ``previous``: compared with its own starts); a step that
    fails ends the chain with the last estimate it had."""
    from tacest.io.slicing import action_ranges, slice_run

    if len(runs) != 1 or runs[0].pose_obs is not None or not runs[0].n_fingers:
        return None, []
    ranges = action_ranges(runs[0])
    previous, steps = None, []
    for k, (_, stop) in enumerate(ranges[:-1]):
        sub = slice_run(runs[0], 0, stop)
        if not np.any(touching(sub)):
            continue  # nothing touched yet: no shape to carry on
        t0 = time.perf_counter()
        try:
            step = Estimator3D([sub], shape_spec, config, effects=effects, previous=previous)
            previous = step.result(step.solve(), time.perf_counter() - t0)
        except SolveFailedError as exc:
            log.info(f"growing horizon: step {k + 1} ({stop} samples) failed ({exc}); the chain ends there")
            steps.append({"samples": int(stop), "status": "failed"})
            break
        steps.append({"samples": int(stop), "status": previous.solver_status, "objective": float(previous.objective),
                      "wall_time": round(time.perf_counter() - t0, 2)})
        log.info(f"growing horizon: step {k + 1} of {len(ranges)} ({stop} of {runs[0].n_samples} samples), "
                 f"objective {previous.objective:.1f} ({time.perf_counter() - t0:.1f} s)")
    return previous, steps


def inertia_parameters(inertia, mass, L) -> np.ndarray:
    """Log-Cholesky parameters (6,) of a physical inertia (3, 3) kg·m² of an object of
    ``mass`` kg at length scale L m (the inverse of Estimator3D.physical's map)."""
    return cholesky_from_inertia(np.asarray(inertia, float) / (mass * L * L))

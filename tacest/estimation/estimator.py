"""``estimate(runs, shape, config)``: the implicit (physics-residual) estimator, end to end.

Pipeline: scales → shape start → consistent initial guess → staged homotopy solves
(IPOPT) → unscaled trajectories, per-sample residuals, observed information → an
:class:`tacest.io.estimate.Estimate`.  A failed IPOPT solve raises SolveFailedError.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from tacest.errors import TacestError
from tacest.estimation.config import EstimatorConfig
from tacest.estimation.data import GRAVITY, Scales, choose_scales, parameter_vector, touching
from tacest.estimation.initial import initial_extents, initial_guess, start_shape_candidates, start_trajectories
from tacest.estimation.problem import PHYSICS_TERMS, SQUARED_TERMS, TERMS, RunStructure
from tacest.estimation.solver import (FATAL_STATUSES, SUCCESS_STATUSES, SolveOutcome, check_success, get_solver,
                                     attempts_json, solve_from_starts)
from tacest.geometry.shapes import make_shape
from tacest.io.estimate import Estimate, RunEstimate
from tacest.io.h5util import sha256_file
from tacest.io.run import Run

#: log(I / I_uniform) bounds: below, a ring-like mass distribution; ln 2 keeps
#: I <= m · r_max² for any convex shape (physically valid)
LOG_INERTIA_BOUNDS = (-1.5, float(np.log(2.0)))
LOG_MASS_BOUNDS = (-6.0, 6.0)
FRICTION_BOUNDS = (0.01, 2.0)
#: half-width (scaled units, relative to max(1, |value|)) of the interval that holds a
#: parameter fixed (estimate_runs' fixed=).  IPOPT removes variables with equal bounds;
#: with the Gauss–Newton Hessian model some such problems failed at iteration 0
#: (Error_In_Step_Computation), while the same problems with the parameters kept as
#: variables in an interval of 2e-9 solve (the diagnosis pins parameters the same way).
#: 1e-9 of a scaled parameter (O(1)) is far below anything the data resolve.
PIN_HALF_WIDTH = 1e-9
#: distance (log mass, or friction) from a bound within which a fitted parameter counts
#: as ended at that bound (IPOPT's interior point stops within ~1e-8 of an active bound)
AT_BOUND_TOLERANCE = 1e-3
#: a mass or friction whose first-order shift without the Occam term (the data alone)
#: exceeds this many of its std is reported as not identifiable: at 2 the data's own
#: optimum lies outside the value's 95 % interval
OCCAM_SHIFT_SIGMAS = 2.0


def _noop(*_a, **_k):
    pass


def check_runs(runs: list[Run], allow_3d: bool = False):
    """One clear error for runs that cannot be estimated together; 3-D runs pass only
    where the caller hands them to the 3-D estimator (estimator3d.py)."""
    if not runs:
        raise TacestError("no run files given")
    dims = {r.dim for r in runs}
    if len(dims) > 1:
        raise TacestError("runs mix 2-D and 3-D recordings; estimate them separately")
    if dims != {2} and not allow_3d:
        raise TacestError("3-D runs are estimated by the implicit method only (--method implicit)")
    for r in runs:
        if r.n_samples < 3:
            raise TacestError(f"{r.filename}: needs at least 3 samples")


class ImplicitEstimator:
    """Implicit estimator for a set of runs of one object (2-D)."""

    def __init__(self, runs: list[Run], shape_spec: str = "box", config: EstimatorConfig | None = None,
                 echo=None, effects=()):
        check_runs(runs)
        self.runs = runs
        self.config = config or EstimatorConfig()
        self.echo = echo or _noop
        self.shape = make_shape(shape_spec, dim=2)
        self.scales: Scales = choose_scales(runs, self.config)
        self.structures = [RunStructure(T=r.n_samples, F=r.n_fingers, observed=r.pose_obs is not None) for r in runs]
        self.has_force = any(r.force is not None for r in runs)
        size_bounds = [float(r.prior["size_bound"]) for r in runs if "size_bound" in r.prior]
        self.size_bound = min(size_bounds) if size_bounds else self.config.prior.size_bound
        w, h = initial_extents(runs, self.scales.L)
        self.s0 = self.shape.initial(w / self.scales.L, h / self.scales.L)
        t0 = time.perf_counter()
        self.built = get_solver(self.shape, self.structures, self.config, effects)
        self.build_time = time.perf_counter() - t0
        self.problem = self.built.problem
        #: scaled theta held fixed (estimate_runs' ``fixed=``), and the warm trajectories
        #: {run index: (Q, V, LG, LF) scaled} that start the solve; None / empty: neither
        self.fixed_theta = None
        self.refit_shape = False
        self.warm_blocks = {}
        #: one dict per solve of :meth:`solve` (start_shape, status, objective,
        #: physics_per_sample; or status "failed" and error)
        self.attempts = []

    # --------------------------------------------------------------------------------
    def variable_bounds(self):
        """lbx, ubx (scaled) of the decision vector: shape, parameter and impulse bounds,
        finger impulses fixed at 0 where the fingertip did not touch, and the gauge."""
        pr = self.problem
        lbx = np.full(pr.n_z, -np.inf)
        ubx = np.full(pr.n_z, np.inf)
        ns = pr.n_shape
        lo, hi = self.shape.bounds(self.size_bound / self.scales.L)
        lbx[:ns], ubx[:ns] = lo, hi
        lbx[ns:ns + 4] = [LOG_MASS_BOUNDS[0], LOG_INERTIA_BOUNDS[0], FRICTION_BOUNDS[0], FRICTION_BOUNDS[0]]
        ubx[ns:ns + 4] = [LOG_MASS_BOUNDS[1], LOG_INERTIA_BOUNDS[1], FRICTION_BOUNDS[1], FRICTION_BOUNDS[1]]
        if not self.has_force:  # DESIGN: without a force stream mass is not identifiable
            # held at the prior's value in a tiny interval, not by equal bounds (see
            # PIN_HALF_WIDTH: equal bounds made some final stages fail at iteration 0)
            lbx[ns], ubx[ns] = -PIN_HALF_WIDTH, PIN_HALF_WIDTH
        a = ns + 4  # effect parameters (problem.NLP_EFFECTS)
        for j, (_, _, _, _, lo_e, hi_e) in enumerate(pr.effect_params):
            lbx[a + j], ubx[a + j] = lo_e, hi_e
        for i, (run, st) in enumerate(zip(self.runs, self.structures)):
            off = pr.offsets[i]
            a, n = off["LG"]
            normal_rows = np.tile(np.arange(2 * pr.K) < pr.K, n // (2 * pr.K))
            lbx[a: a + n][normal_rows] = 0.0  # lambda_n >= 0 (tangential impulses are free)
            if pr.n_impact:  # restitution's impact memory holds approach speeds (m/s, >= 0)
                a, n = off["S"]
                memory_rows = np.tile(np.arange(pr.n_state) >= pr.n_plate, n // max(pr.n_state, 1))
                lbx[a: a + n][memory_rows] = 0.0
            if st.F:
                # finger impulses exist only where the tactile flag says the finger touched
                a, n = off["LF"]
                on = touching(run)[1:]
                off_rows = np.repeat(~on, 2, axis=1)  # (T-1, 2F): [x, y] per finger
                lbx[a: a + n] = np.where(off_rows, 0.0, -np.inf).reshape(-1)
                ubx[a: a + n] = np.where(off_rows, 0.0, np.inf).reshape(-1)
        if self.fixed_theta is not None:
            # held fixed (estimate_runs' fixed=): theta and the lifted quantities in an
            # interval of ±PIN_HALF_WIDTH, not equal bounds (see PIN_HALF_WIDTH); a fixed
            # shape has its orientation, so no gauge.  With refit_shape only the
            # parameters after the shape are held (the lifted ones follow theta)
            th = self.fixed_theta
            if self.refit_shape:
                pins = ((pr.n_shape, th[pr.n_shape:]),)
            else:
                pins = ((0, th), (pr.phys_offset, np.asarray(pr.phys_sx(th, self.scales.L, self.scales.m0)).ravel()))
            for a, vals in pins:
                half = PIN_HALF_WIDTH * np.maximum(1.0, np.abs(vals))
                lbx[a: a + len(vals)] = vals - half
                ubx[a: a + len(vals)] = vals + half
        if (self.fixed_theta is None or self.refit_shape) and self.shape.name != "box" \
                and not any(r.pose_obs is not None for r in self.runs):
            # gauge: a free polygon can rotate in its body frame; fix the start angle of run 0
            a = pr.offsets[0]["Q"][0] + 2
            lbx[a] = ubx[a] = self.z[a]
        return lbx, ubx

    def params(self, eps, comp_mult, dyn_mult=1.0):
        return parameter_vector(self.problem, self.runs, self.scales, self.config, eps, comp_mult, self.s0,
                                dyn_mult=dyn_mult)

    # --------------------------------------------------------------------------------
    def impulse_only_bounds(self, lbx, ubx):
        """Bounds that hold everything but the contact impulses at the current z.  (Not
        the parameters too, even on observed poses: with the noisy observed trajectory
        held, the dynamics residual of a light object is cheapest, and such a stage
        ran to the mass bound.)"""
        pr = self.problem
        free = np.zeros(pr.n_z, bool)
        for off in pr.offsets:
            for b in ("LG", "LF", "S"):  # the plate's sink follows its load
                a, n = off[b]
                free[a: a + n] = True
        return np.where(free, lbx, self.z), np.where(free, ubx, self.z)

    def solve(self) -> SolveOutcome:
        """Staged solve from the best starting shape; when that fit fails, or violates its
        own physics by more than ``solver.restart_physics`` objective units per sample
        (a local minimum where the object floats, sinks or slides against friction to
        follow the touches), again from up to ``solver.restarts`` other starting shapes
        (initial.start_shape_candidates), keeping the successful fit of lowest objective.

        Each solve:

        1. "impulses": the contact impulses alone, with the initial trajectory, shape and
           parameters held (a convex least-squares problem), so that every later stage
           starts from a physically consistent point (small residuals, where the
           Gauss–Newton model is good);
        2. the homotopy stages of the config, everything free.
        """
        pr = self.problem
        if self.fixed_theta is not None:
            starts = [self.fixed_theta[: pr.n_shape].copy()]
        else:
            starts = start_shape_candidates(pr, self.runs, self.scales, self.s0, 1 + int(self.config.solver.restarts))

        def solve_one(s0):
            out = self._solve_from(s0)
            return out, self.physics_per_sample(out.z), (s0, self.p_final)

        self.attempts = []
        out, (self.s0, self.p_final) = solve_from_starts(
            [({"start_shape": np.asarray(s0, float)}, s0) for s0 in starts], solve_one,
            self.config.solver.restart_physics, self.echo, self.attempts)
        self.z = out.z
        return out

    def physics_per_sample(self, z) -> float:
        """Objective units per sample of the physics terms (:data:`PHYSICS_TERMS`) at z
        with the final stage's parameters: how far a fit violates its own model."""
        t, _ = self.problem.term_fun(z, self.p_final)
        t = dict(zip(TERMS, np.asarray(t, float).ravel()))
        return sum(t[k] for k in PHYSICS_TERMS) / sum(st.T for st in self.structures)

    def _solve_from(self, s0) -> SolveOutcome:
        """One staged solve (see :meth:`solve`) from the starting shape s0 (scaled)."""
        cfg = self.config.solver
        pr = self.problem
        self.s0 = np.asarray(s0, float)
        trajectories = start_trajectories(pr, self.runs, self.scales, self.s0)
        self.z = initial_guess(pr, self.runs, self.scales, self.s0, trajectories)
        if self.fixed_theta is not None:
            self.z[: pr.n_theta] = self.fixed_theta
            self.z[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(
                pr.phys_sx(self.fixed_theta, self.scales.L, self.scales.m0)).reshape(-1)
        for i, (Q, Vv, LG, LF) in self.warm_blocks.items():
            pr.set_run_blocks(self.z, i, Q=Q, V=Vv, LG=LG, LF=LF)
        stages = []
        hom = list(cfg.homotopy)
        plan = [("impulses", *hom[0], "impulses")]
        for k, (eps, w, wd) in enumerate(hom):
            plan.append((f"homotopy {k + 1}/{len(hom)}", eps, w, wd, "all"))
        lam_x = lam_g = None
        total_t = 0.0
        for label, eps, w, wd, which in plan:
            lbx, ubx = self.variable_bounds()
            lbg, ubg = pr.lbg, pr.ubg
            if which == "impulses":
                self.z = self.settle_states(self.z, self.params(eps, w, wd))
                lbx, ubx = self.impulse_only_bounds(lbx, ubx)
            self.z = np.clip(self.z, lbx, ubx)
            mode = cfg.hessian
            if mode == "gauss-newton-then-exact":
                mode = "exact" if label == plan[-1][0] and len(plan) > 2 else "gauss-newton"
            max_iter = cfg.max_iter if label == plan[-1][0] else cfg.stage_max_iter
            sol, info = self.built.solve(self.z, self.params(eps, w, wd), lbx, ubx, lbg, ubg, lam_x, lam_g,
                                         label=label, echo=self.echo, hessian=mode, max_iter=max_iter)
            stages.append(info)
            total_t += info.wall_time
            self.echo(f"stage {label}: {info.status}, {info.iterations} iterations, "
                      f"objective {info.objective:.6g}, {info.wall_time:.1f} s")
            final = label == plan[-1][0]
            if final or info.status in FATAL_STATUSES:
                check_success(info)
            # the impulses stage and an intermediate homotopy stage only prepare the next
            # one: the iterate is used whether or not IPOPT met its tolerance within the
            # stage's budget (on observed poses, whose noise the impulses cannot follow
            # exactly, the impulses stage can crawl to its budget)
            self.z = np.asarray(sol["x"]).reshape(-1)
            if which == "all":
                lam_x = np.asarray(sol["lam_x"]).reshape(-1)
                lam_g = np.asarray(sol["lam_g"]).reshape(-1)
        last = stages[-1]
        self.p_final = self.params(*plan[-1][1:4])
        return SolveOutcome(z=self.z, lam_g=lam_g, lam_x=lam_x, status=last.status,
                            success=last.status in SUCCESS_STATUSES,
                            iterations=sum(s.iterations for s in stages), wall_time=total_t,
                            objective=last.objective, stages=stages)

    # --------------------------------------------------------------------------------
    def physical(self, z):
        V, mass, inertia, mu_g, mu_f, area = self.problem.phys_fun(z, self.p_final)
        return (np.array(V), float(mass), float(inertia), float(mu_g), float(mu_f))

    def _stage_outputs(self, z, i):
        """All stage-function outputs of run i at z: {name: (n_out, T-1)}."""
        pr = self.problem
        st = self.structures[i]
        g, D = self._run_data(i)
        out = pr.stage_funs[i].map(st.T - 1)(*pr.stage_arguments(z, i, D, g))
        return dict(zip(pr.stage_funs[i].name_out(), out))

    def _run_data(self, i, p=None):
        """(g, D): run i's global vector and data matrix (n_data, T) in the parameter
        vector p (default: the final stage's)."""
        pr = self.problem
        a, ng, nd = pr.p_offsets[i]
        p = self.p_final if p is None else p
        return p[a: a + ng], p[a + ng: a + ng + nd].reshape(self.structures[i].T, -1).T

    def settle_states(self, z, p):
        """z with restitution's impact memory following its law along z's trajectories
        (Problem2D.settle_impact_memory) under the parameter vector p; called before
        every impulse stage."""
        for i in range(len(self.structures)):
            g, D = self._run_data(i, p)
            z = self.problem.settle_impact_memory(z, i, D, g)
        return z

    def per_sample_residuals(self, z, i):
        """{term: (T,)} value of each loss term per sample of run i (0.5 ||r||² for the
        squared terms, the penalty value for the others), weights not applied."""
        pr = self.problem
        g, D = self._run_data(i)
        res = self._stage_outputs(z, i)
        o0 = dict(zip(pr.start_funs[i].name_out(), pr.start_funs[i](*pr.start_arguments(z, i, D, g))))
        result = {}
        for t in TERMS:
            arr = np.asarray(res[t])
            vals = 0.5 * np.sum(arr**2, axis=0) if t in SQUARED_TERMS else arr.reshape(-1)
            first = 0.0
            if t == "dynamics":
                first = 0.5 * float(ca.sumsqr(o0["rest"]))
            elif t in ("penetration", "pose", "contact"):
                first = 0.5 * float(ca.sumsqr(o0[t]))
            result[t] = np.concatenate([[first], vals])
        result["kinematics"] = np.concatenate([[0.0], np.linalg.norm(np.asarray(res["g_kin"]), axis=0)])
        return result

    def trajectories(self, z, i):
        """Unscaled pose (T, 3), velocity (T, 3) and impulses of run i."""
        Q, Vv, LG, LF = self.problem.run_blocks(z, i)
        L = self.scales.L
        scale = np.array([L, L, 1.0])
        pose = Q.T * scale
        vel = Vv.T * scale
        run = self.runs[i]
        Lam = self.scales.m0 * GRAVITY * run.dt
        K = self.problem.K
        T = run.n_samples
        res = self._stage_outputs(z, i)
        imp = {
            "ground_normal": np.vstack([np.zeros((1, K)), LG[:K].T * Lam]),
            "ground_tangent": np.vstack([np.zeros((1, K)), LG[K:].T * Lam]),
        }
        F = self.structures[i].F
        fi = np.asarray(res["imp_finger"]).T  # (T-1, 2F)
        for f in range(F):
            imp[f"finger_{f}"] = np.vstack([np.zeros((1, 2)), fi[:, 2 * f: 2 * f + 2]])
        assert imp["ground_normal"].shape[0] == T
        return pose, vel, imp


def core_theta_of(problem, scales: Scales, estimate: Estimate, what: str = "the estimate") -> np.ndarray:
    """Scaled theta before the effect block, [shape s, log(m/m0), log(I/I_uniform),
    mu_ground, mu_finger], of a 2-D estimate's vertices and parameters (the inverse of the
    problem's theta -> physical map); a TacestError naming ``what`` when the estimate
    does not fit the problem's shape or lacks a parameter."""
    from tacest.geometry.shapes import polygon_area_centroid_j

    L, m0 = scales.L, scales.m0
    V = np.asarray(estimate.vertices, float)
    if estimate.dim != 2 or V.ndim != 2 or V.shape[1] != 2:
        raise TacestError(f"{what} is not a 2-D estimate")
    if problem.shape.name == "box":
        s = np.array([np.ptp(V[:, 0]), np.ptp(V[:, 1])]) / L
    else:
        if V.shape[0] != problem.K:
            raise TacestError(f"{what} has {V.shape[0]} vertices, the shape {problem.shape.name} has {problem.K}")
        s = V.reshape(-1) / L
    try:
        mass, inertia = float(estimate.params["mass"]), float(estimate.params["inertia"])
        mu_g, mu_f = float(estimate.params["friction_ground"]), float(estimate.params["friction_finger"])
    except KeyError as exc:
        raise TacestError(f"{what} has no parameter {exc.args[0]!r}") from None
    area, _, J = polygon_area_centroid_j(V)
    return np.concatenate([s, [np.log(mass / m0), np.log(inertia / (mass * float(J) / float(area))), mu_g, mu_f]])


def fixed_theta_of(est: "ImplicitEstimator", fixed: Estimate) -> np.ndarray:
    """Scaled theta of the problem from an estimate's parameters (shape from its
    vertices, mass, inertia, frictions, effect parameters): what ``fixed=`` holds."""
    from tacest.estimation.augment import effect_theta

    core = core_theta_of(est.problem, est.scales, fixed, "the fixed estimate")
    theta = np.concatenate([core, effect_theta(est.problem.effects, est.problem.K, fixed.params, est.scales.L,
                                               est.scales.m0, float(fixed.params["friction_ground"]))])
    if not np.all(np.isfinite(theta)):
        raise TacestError("the fixed estimate has non-finite parameters")
    return theta


def warm_blocks_of(est: "ImplicitEstimator", fixed: Estimate) -> dict:
    """{run index: scaled (Q, V, LG, LF)} from the trajectories of ``fixed`` for the runs
    it estimated (same source file, or the same position in the list, and the same
    number of samples); velocities re-derived from the poses (eq. D2 holds)."""
    out = {}
    pr = est.problem
    scale = np.array([est.scales.L, est.scales.L, 1.0])
    for i, run in enumerate(est.runs):
        cands = [r for r in fixed.runs if run.filename and r.source_file == run.filename]
        if not cands and len(fixed.runs) == len(est.runs):
            cands = [fixed.runs[i]]
        cands = [r for r in cands if np.asarray(r.pose).shape[0] == run.n_samples]
        if not cands:
            continue
        wr = cands[0]
        K, F, T = pr.K, run.n_fingers, run.n_samples
        Lam = est.scales.m0 * GRAVITY * run.dt
        Q = (np.asarray(wr.pose, float)[:, :3] / scale).T
        Vv = np.zeros_like(Q)
        Vv[:, 1:] = np.diff(Q, axis=1) / run.dt
        imp = wr.impulses
        LG = None
        gn, gt = imp.get("ground_normal"), imp.get("ground_tangent")
        if gn is not None and gt is not None and np.shape(gn) == (T, K) and np.shape(gt) == (T, K):
            LG = np.vstack([np.maximum(np.asarray(gn, float)[1:] / Lam, 0.0).T, (np.asarray(gt, float)[1:] / Lam).T])
        LF = None
        if F and all(np.shape(imp.get(f"finger_{f}", ())) == (T, 2) for f in range(F)):
            LFt = np.concatenate([np.asarray(imp[f"finger_{f}"], float)[1:] for f in range(F)], axis=1)
            LF = (LFt * np.repeat(touching(run)[1:], 2, axis=1) / Lam).T  # off-contact impulses are 0
        out[i] = (Q, Vv, LG, LF)
    return out


def estimate_runs(runs: list[Run], shape_spec: str = "box", config: EstimatorConfig | None = None,
                  echo=None, method: str = "implicit", effects=(), fixed: Estimate | None = None,
                  refit_shape: bool = False) -> Estimate:
    """Estimate one object's parameters and each run's trajectory.  See module docstring.

    effects : SPEC effect names modelled as extra parameters inside the NLP
        (problem.NLP_EFFECTS; docs/diagnosis.md gives each augmentation's equations);
        their values appear in ``Estimate.params`` as ``effect.parameter``
        (tacest.estimation.augment) and in the information matrix;
    fixed : an Estimate whose parameters (shape, mass, inertia, frictions and the
        effect parameters of ``effects``) are held fixed: only trajectories and
        impulses are fitted (held-out evaluation); its trajectories start the runs it
        estimated (same source file and length);
    refit_shape : with ``fixed``, hold everything but the shape, which is refitted from
        the fixed estimate's (a held-out piece may touch faces the fixed fit never saw).
    """
    from tacest.information.observed import observed_information
    from tacest.estimation.problem import check_effects

    echo = echo or _noop
    t_start = time.perf_counter()
    effects = check_effects(effects)
    if (effects or fixed is not None) and method != "implicit":
        raise TacestError("effects= and fixed= are offered by the implicit 2-D estimator only")
    if method == "shooting":
        from tacest.estimation.shooting import estimate_shooting

        return estimate_shooting(runs, shape_spec, config, echo)
    if method != "implicit":
        raise TacestError(f"unknown method {method!r}: use implicit or shooting")
    check_runs(runs, allow_3d=True)
    if runs[0].dim == 3:  # the one place where 2-D and 3-D part
        from tacest.estimation.estimator3d import estimate_runs_3d

        if effects or fixed is not None:
            raise TacestError("effects= and fixed= are offered by the implicit 2-D estimator only")
        return estimate_runs_3d(runs, shape_spec, config, echo)
    est = ImplicitEstimator(runs, shape_spec, config, echo, effects=effects)
    if fixed is not None:
        est.fixed_theta = fixed_theta_of(est, fixed)
        est.refit_shape = bool(refit_shape)
        est.warm_blocks = warm_blocks_of(est, fixed)
    echo(f"built NLP: {est.problem.n_z} variables, {est.problem.g.shape[0]} constraints "
         f"({est.build_time:.1f} s)" + (f", effects: {', '.join(effects)}" if effects else ""))
    out = est.solve()
    V, mass, inertia, mu_g, mu_f = est.physical(out.z)
    run_ests = []
    for i, run in enumerate(runs):
        pose, vel, imp = est.trajectories(out.z, i)
        res = est.per_sample_residuals(out.z, i)
        src = run.filename or ""
        sha = sha256_file(src) if src else ""
        run_ests.append(RunEstimate(pose=pose, velocity=vel, impulses=imp, residuals=res,
                                    source_file=src, source_sha256=sha))
    # held fixed: no parameter is estimated, so there is no information to report
    # std: the data's own (whether the data determine a parameter, below); std_post: the
    # posterior's (data and priors), the uncertainty the estimate reports
    info, names, std, shift, std_post = (observed_information(est, out.z, penalty_shift=True, posterior=True)
                                         if fixed is None else (None, [], {}, {}, {}))
    params = {"mass": mass, "inertia": inertia, "friction_ground": mu_g, "friction_finger": mu_f}
    if effects:
        from tacest.estimation.augment import effect_params

        params.update(effect_params(est.problem, out.z, est.scales.L, est.scales.m0))
    identifiable = {
        "mass": est.has_force,
        "inertia": est.has_force,
        "friction_ground": True,
        "friction_finger": any(r.n_fingers for r in runs),
    }
    # a parameter the data leave (nearly) undetermined: one-sigma above half its value
    for k in ("friction_ground", "friction_finger", "mass"):
        if k in std and not std[k] <= 0.5 * max(params[k], 1e-3):
            identifiable[k] = False
    # a parameter that ended at its hard bound is held there by the bound, not the data
    # (e.g. a light object with ground friction 2 that balances slow pushes statically;
    # docs/estimation.md, "Pose observations and light objects")
    def ended_at_bound(u, bounds):
        return not bounds[0] + AT_BOUND_TOLERANCE < u < bounds[1] - AT_BOUND_TOLERANCE

    at_bound = {"mass": ended_at_bound(np.log(mass / est.scales.m0), LOG_MASS_BOUNDS),
                "friction_ground": ended_at_bound(mu_g, FRICTION_BOUNDS),
                "friction_finger": ended_at_bound(mu_f, FRICTION_BOUNDS)}
    for k, hit in at_bound.items():
        if hit and identifiable.get(k) and fixed is None:
            identifiable[k] = False
            echo(f"warning: {k} = {params[k]:.4g} ended at its bound: the data do not determine it")
    # a parameter the Occam term, not the data, put where it is: without the term the
    # data alone would move it by more than OCCAM_SHIFT_SIGMAS of its std (on slow
    # sliding pushes the data cannot split the push force into mass and ground friction,
    # docs/estimation.md, "Pose observations and light objects")
    for k in ("mass", "friction_ground", "friction_finger"):
        if identifiable.get(k) and abs(shift.get(k, 0.0)) > OCCAM_SHIFT_SIGMAS * std.get(k, np.inf):
            identifiable[k] = False
            echo(f"warning: {k} = {params[k]:.4g} is set by the Occam term, not the data (without it the data "
                 f"would move it by {shift[k]:+.3g}, std {std[k]:.3g})")
    for k in std:  # effect parameters: identifiable where the data bound them
        if "." in k:
            identifiable[k] = bool(np.isfinite(std[k]))
    if "force_scale" in effects:
        # every force in the model (weight, inertia, contacts) scales with the mass, the
        # measured ones with the gain: only gain × mass is identifiable (docs/diagnosis.md)
        identifiable["mass"] = identifiable["force_scale.gain"] = False
    if fixed is not None:  # held fixed: nothing was estimated
        identifiable = {k: False for k in identifiable}
    wall = time.perf_counter() - t_start
    return Estimate(
        dim=2, shape=est.shape.name, vertices=V, params=params, runs=run_ests, model=list(effects),
        solver_status=out.status, success=out.success, iterations=out.iterations, wall_time=wall,
        objective=out.objective, information=info, info_names=names, std=std_post, identifiable=identifiable,
        config=est.config.to_dict(), method="implicit",
        extra_attrs={"stages": "; ".join(f"{s.name}: {s.status} ({s.iterations} it, {s.wall_time:.2f} s)"
                                          for s in out.stages),
                     "length_scale": est.scales.L, "mass_scale": est.scales.m0,
                     "starts": attempts_json(est.attempts)},
    )

"""The implicit (physics-residual) estimator for 2-D runs, end to end.

Pipeline: scales → starting shapes → consistent initial guess (initial.py) → the one
staged solve (solver.py: impulses alone, then the homotopy; restarts from other starting
shapes) → unscaled trajectories, per-sample residuals, observed information
(uncertainty.py) → an Estimate (result.py).  A failed IPOPT solve raises
SolveFailedError.

The same estimator serves the diagnosis: effects as extra parameters (``effects=``,
tacest.model.registry), parameters held fixed (pins: all of theta, the shape only, or
everything but the shape), and warm starts from an earlier estimate's parameters and
trajectories (:func:`warm_start`).
"""

from __future__ import annotations

import logging
import time

import casadi as ca
import numpy as np

from tacest.errors import TacestError
from tacest.estimation.sensor_noise import judged_params, settings_for
from tacest.estimation.bounds import FRICTION_BOUNDS, LOG_INERTIA_BOUNDS, LOG_MASS_BOUNDS
from tacest.estimation.config import EstimatorConfig, solver_structure_key, start_workers
from tacest.estimation.data import (Scales, choose_scales, force_in_contact, parameter_vector, previous_trajectories,
                                    touching)
from tacest.estimation.initial import continued_trajectory, initial_extents, initial_guess, start_shape_candidates
from tacest.estimation.problem2d import Problem2D, RunStructure
from tacest.estimation.fitquality import goodness_of_fit
from tacest.estimation.result import FitFacts, assemble, ended_at_bound, shape_params_at_bound, shape_seen, start_verdict
from tacest.estimation.smc2d import SMCSettings, smc_start
from tacest.estimation.smc import best_lineages
from tacest.estimation.solver import (SOLVER_CACHE_LIMIT, BuiltSolver, SolverCache, map_in_processes, plan_stages, pin,
                                      run_stages, solve_from_starts, SolveOutcome)
from tacest.estimation.uncertainty import information_names_2d, observed_information_2d, vertex_jacobian
from tacest.geometry.shapes import make_shape, numeric_vertices, polygon_area_centroid_j
from tacest.io.estimate import Estimate, RunEstimate
from tacest.io.run import Run, run_sha256
from tacest.model.stage2d import PHYS_NAMES, PHYSICS_TERMS, SQUARED_TERMS, TERMS

log = logging.getLogger(__name__)

#: what a pinned fit holds (see ImplicitEstimator): all of theta, the shape only, or
#: everything but the shape (mass, inertia, frictions, effect parameters)
PIN_MODES = ("all", "shape", "physics")

#: built NLPs and solvers by structure (shape, runs, settings, effects): the diagnosis
#: refits the same structures many times (the most recent SOLVER_CACHE_LIMIT kept)
_SOLVERS = SolverCache(limit=SOLVER_CACHE_LIMIT)


def check_runs(runs: list[Run]):
    """One clear error for runs that the 2-D estimator cannot use together."""
    if not runs:
        raise TacestError("no run files given")
    for r in runs:
        if r.dim != 2:
            raise TacestError(f"{r.filename or 'run'}: is {r.dim}-D; the 2-D estimator needs 2-D runs")
        if r.n_samples < 3:
            raise TacestError(f"{r.filename}: needs at least 3 samples")


def solver_for(shape, structures, config: EstimatorConfig, effects=()) -> BuiltSolver:
    """The cached built solver of this structure and model (built on first use)."""
    from tacest.model.registry import names_of, resolve

    effects = names_of(resolve(effects, 2))
    key = (shape.name, tuple(structures), solver_structure_key(config.solver), config.weights.occam > 0,
           config.noise.complementarity_reach > 0, effects)
    return _SOLVERS.get(key, lambda: BuiltSolver(Problem2D(shape, structures, config, effects=effects), config))


class ImplicitEstimator:
    """Implicit estimator for a set of 2-D runs of one object.

    effects : effect names modelled as extra parameters (tacest.model.registry);
    pinned_theta, pin : scaled theta to hold (tacest.estimation.solver.pin) and what of
        it: ``all``, ``shape`` or ``physics`` (everything but the shape).
    """

    #: z0 (scaled) of a start from an earlier estimate of the first samples of these
    #: runs (:func:`previous_start_2d`), or None
    previous_z = None

    def __init__(self, runs: list[Run], shape_spec: str = "box", config: EstimatorConfig | None = None,
                 effects=(), pinned_theta=None, pin: str = "all", previous: Estimate | None = None):
        check_runs(runs)
        if pin not in PIN_MODES:
            raise TacestError(f"internal: pin must be one of {PIN_MODES}, got {pin!r}")
        self.runs = runs
        #: the fit's settings (touch alone: the sensors' noise levels as the runs show
        #: them where larger) and the report of those levels (sensor_noise.py)
        self.config, self.sensor_noise = settings_for(runs, config or EstimatorConfig())
        self.shape = make_shape(shape_spec, dim=2)
        # a mismatched earlier estimate is an error before the NLP is built
        before = None if previous is None else previous_trajectories(previous, 2, self.shape.name, runs)
        self.scales: Scales = choose_scales(runs, self.config)
        self.structures = [RunStructure(T=r.n_samples, F=r.n_fingers, observed=r.pose_obs is not None) for r in runs]
        self.has_force = force_in_contact(runs)  # a force measured in contact: the mass is told
        size_bounds = [float(r.prior["size_bound"]) for r in runs if "size_bound" in r.prior]
        self.size_bound = min(size_bounds) if size_bounds else self.config.prior.size_bound
        w, h = initial_extents(runs, self.scales.L)
        self.s0 = self.shape.initial(w / self.scales.L, h / self.scales.L)
        t0 = time.perf_counter()
        self.built = solver_for(self.shape, self.structures, self.config, effects)
        self.build_time = time.perf_counter() - t0
        self.problem: Problem2D = self.built.problem
        self.pinned_theta = None if pinned_theta is None else np.asarray(pinned_theta, float)
        self.pin = pin
        self.previous_z = None if previous is None else previous_start_2d(self, previous, before)
        #: one dict per solve of :meth:`solve` (start_shape, status, objective,
        #: physics_per_sample; or status "failed" and error)
        self.attempts = []
        self.z = None
        self.p_final = None
        self.bounds_final = None

    # --------------------------------------------------------------------------------
    # bounds and parameters

    def variable_bounds(self, z):
        """lbx, ubx (scaled) of the decision vector at z: shape, parameter and impulse
        bounds, finger impulses fixed at 0 where the fingertip did not touch, the states'
        bounds, the pins, and the gauge."""
        pr = self.problem
        lbx = np.full(pr.n_z, -np.inf)
        ubx = np.full(pr.n_z, np.inf)
        ns = pr.n_shape
        lbx[:ns], ubx[:ns] = self.shape.bounds(self.size_bound / self.scales.L)
        lbx[ns:ns + 4] = [LOG_MASS_BOUNDS[0], LOG_INERTIA_BOUNDS[0], FRICTION_BOUNDS[0], FRICTION_BOUNDS[0]]
        ubx[ns:ns + 4] = [LOG_MASS_BOUNDS[1], LOG_INERTIA_BOUNDS[1], FRICTION_BOUNDS[1], FRICTION_BOUNDS[1]]
        if not self.has_force:  # DESIGN: without a force measured in contact mass is not identifiable
            pin(lbx, ubx, [ns], [0.0])  # held at the prior's value
        a = ns + len(PHYS_NAMES)  # effect parameters
        for j, (e, p) in enumerate(pr.effect_params):
            lbx[a + j], ubx[a + j] = e.bounds(p, self.config, self.scales.L, lbx[:ns])
        state_lo = pr.state_lower_bounds()
        for i, (run, st) in enumerate(zip(self.runs, self.structures)):
            off = pr.offsets[i]
            a, n = off["LG"]
            normal_rows = np.tile(np.arange(2 * pr.K) < pr.K, n // (2 * pr.K))
            lbx[a: a + n][normal_rows] = 0.0  # lambda_n >= 0 (tangential impulses are free)
            if pr.n_state:
                a, n = off["S"]
                lbx[a: a + n] = np.tile(state_lo, st.T)
            if st.F:
                # finger impulses exist only where the tactile flag says the finger touched
                a, n = off["LF"]
                on = touching(run)[1:]
                off_rows = np.repeat(~on, 2, axis=1)  # (T-1, 2F): [x, y] per finger
                lbx[a: a + n] = np.where(off_rows, 0.0, -np.inf).reshape(-1)
                ubx[a: a + n] = np.where(off_rows, 0.0, np.inf).reshape(-1)
        if self.pinned_theta is not None:
            th = self.pinned_theta
            if self.pin == "shape":
                # the shape alone: the lifted vertices follow from the constraint phys = phys(theta)
                pin(lbx, ubx, np.arange(ns), th[:ns])
            elif self.pin == "physics":
                pin(lbx, ubx, np.arange(ns, pr.n_theta), th[ns:])
            else:
                pin(lbx, ubx, np.arange(pr.n_theta), th)
                phys = np.asarray(pr.phys_sx(th, self.scales.L, self.scales.m0)).reshape(-1)
                pin(lbx, ubx, pr.phys_offset + np.arange(pr.n_phys), phys)
        shape_free = self.pinned_theta is None or self.pin == "physics"
        if shape_free and self.shape.name != "box" and not any(r.pose_obs is not None for r in self.runs):
            # gauge: a free polygon can rotate in its body frame; fix the start angle of run 0
            a = pr.offsets[0]["Q"][0] + 2
            lbx[a] = ubx[a] = z[a]
        return lbx, ubx

    def stage_bounds(self, stage, z):
        """The bounds of a stage at z: an impulses-only stage holds everything but the
        contact impulses and the states at z.  (Not the parameters too, even on observed
        poses: with the noisy observed trajectory held, the dynamics residual of a light
        object is cheapest, and such a stage ran to the mass bound.)"""
        lbx, ubx = self.variable_bounds(z)
        if not stage.impulses_only:
            return lbx, ubx
        pr = self.problem
        free = np.zeros(pr.n_z, bool)
        for off in pr.offsets:
            for b in ("LG", "LF", "S"):  # the states follow their loads
                a, n = off[b]
                free[a: a + n] = True
        return np.where(free, lbx, z), np.where(free, ubx, z)

    def params(self, eps, comp_mult, dyn_mult=1.0, ridge=None):
        return parameter_vector(self.problem, self.runs, self.scales, self.config, eps, comp_mult, self.s0,
                                dyn_mult=dyn_mult, ridge=self.ridge() if ridge is None else ridge)

    def ridge(self) -> float:
        """The Hessian model's ridge: solver.hessian_ridge_observed where some run has pose
        observations, solver.hessian_ridge otherwise."""
        cfg = self.config.solver
        observed = any(r.pose_obs is not None for r in self.runs)
        return float(cfg.hessian_ridge_observed if observed else cfg.hessian_ridge)

    def stage_params(self, stage, retry=False):
        ridge = max(self.ridge(), 1.0) if retry else None
        return self.params(stage.eps, stage.comp_mult, stage.dyn_mult, ridge=ridge)

    def _prepare(self, stage, z, p):
        """Before an impulses stage: the effects' states settled along z's trajectories."""
        return self.settle_states(z, p) if stage.impulses_only else z

    # --------------------------------------------------------------------------------
    # solving

    def stages(self, last_only=False):
        cfg = self.config.solver
        return plan_stages(cfg.homotopy, cfg.hessian, cfg.max_iter, cfg.stage_max_iter, last_only=last_only)

    def own_start(self, s0) -> np.ndarray:
        """Scaled z0 of the estimator's own start from the starting shape s0 (push-tracked
        or observed trajectories, initial.py), with the pinned part of theta set."""
        return self.with_pins(initial_guess(self.problem, self.runs, self.scales, np.asarray(s0, float)))

    def with_pins(self, z) -> np.ndarray:
        """z with the pinned part of theta (and the lifted quantities) set."""
        if self.pinned_theta is None:
            return z
        pr, th = self.problem, self.pinned_theta
        if self.pin == "shape":
            z[: pr.n_shape] = th[: pr.n_shape]
        elif self.pin == "physics":
            z[pr.n_shape: pr.n_theta] = th[pr.n_shape:]
        else:
            z[: pr.n_theta] = th
        z[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(
            pr.phys_sx(z[: pr.n_theta], self.scales.L, self.scales.m0)).reshape(-1)
        return z

    def solve_from(self, z0, last_only=False, accept_budget=False, abandon_above=float("inf"), multipliers=None,
                   stop_stalled=False) -> SolveOutcome:
        """One staged solve (solver.run_stages) from z0 (scaled): impulses alone, then
        every homotopy stage, or only the last one (``last_only``: z0 is already a
        solution of a nearby problem).  ``accept_budget``: a final stage that uses up its
        budget, or stalls (``stop_stalled``), keeps its last iterate (success False);
        ``abandon_above``: the best fit's objective so far, far above which the final
        stage stops (StartAbandoned); ``multipliers``:
        (lam_x, lam_g) that warm-start the first stage that frees everything;
        ``stop_stalled``: a final stage that stalls (solver.STALL_RULE) stops, its last
        iterate kept as a budget fit (with ``accept_budget``: the search over starts, as
        ``solver.stop_stalled`` says, which resumes a stalled fit that it keeps)."""
        stages = self.stages(last_only)
        lam_x, lam_g = multipliers if multipliers is not None else (None, None)
        out = run_stages(self.built, z0, stages, self.stage_params, self.stage_bounds, prepare=self._prepare,
                         accept_budget=accept_budget, abandon_above=abandon_above, lam_x0=lam_x, lam_g0=lam_g,
                         stop_stalled=stop_stalled)
        self.z = out.z
        self.p_final = self.stage_params(stages[-1])
        self.bounds_final = self.variable_bounds(out.z)
        return out

    def solve(self) -> SolveOutcome:
        """Staged solves from the best start; when that fit fails, or violates its own
        physics by more than ``solver.restart_physics`` objective units per sample (a
        local minimum where the object floats, sinks or slides against friction to follow
        the touches), again from up to ``solver.restarts`` other starts, keeping the
        fit of lowest objective (one that used up its iteration budget included, with its
        status: solver.solve_from_starts).

        The starts: the sampler's (smc2d.py: the lineage of the best of
        ``solver.sampler_particles`` hypotheses followed through the runs) where every
        run is without pose observations and touched, then push-tracked starting shapes
        (initial.start_shape_candidates).  A pinned shape is the only start."""
        pr = self.problem
        if self.pinned_theta is not None and self.pin in ("all", "shape"):
            starts = [({"start_shape": self.pinned_theta[: pr.n_shape].copy()}, ("shape", self.pinned_theta[: pr.n_shape]))]
        else:
            starts = [({"start": "sampler", "sampler_seed": s.seed, "start_extents": np.asarray(s.extents, float),
                        "log_likelihood": s.log_likelihood}, ("sampler", s)) for s in self.sampled_starts()]
            n_always = len(starts)
            n = n_always + 1 + int(self.config.solver.restarts)
            starts += [({"start_shape": np.asarray(s0, float)}, ("shape", s0))
                       for s0 in start_shape_candidates(pr, self.runs, self.scales, self.s0, n - len(starts))]
            if self.previous_z is not None:  # an earlier estimate's start: first, and compared
                starts.insert(0, ({"start": "previous estimate"}, ("previous", self.previous_z)))
                n_always += 1
        s_ref = np.array(self.s0, float)  # the shape prior's reference of the push-tracked starts

        def solve_one(start, abandon_above):
            kind, value = start
            if kind == "sampler":
                z0 = self.sampler_z(value)
            elif kind == "previous":  # the shape prior's reference is the start's own shape, as the sampler's
                z0, self.s0 = value.copy(), value[: pr.n_shape].copy()
            else:  # the same reference whichever start ran before (starts may run in other processes)
                self.s0 = s_ref.copy()
                z0 = self.own_start(value)
            out = self.solve_from(z0, accept_budget=True,  # solve_from_starts judges budget fits
                                  abandon_above=abandon_above, stop_stalled=self.config.solver.stop_stalled)
            return judged(out)

        def judged(out):
            return start_verdict(self, out, (self.s0, self.p_final, self.bounds_final))

        def resume(out, saved):  # a stalled fit, kept: its final stage continued without the stall rule
            self.s0, self.p_final, self.bounds_final = saved
            more = self.solve_from(out.z, last_only=True, accept_budget=True, multipliers=(out.lam_x, out.lam_g))
            more.stages, more.iterations = out.stages + more.stages, out.iterations + more.iterations
            more.wall_time += out.wall_time
            return judged(more)

        self.attempts = []
        pinned = self.pinned_theta is not None and self.pin in ("all", "shape")
        out, (self.s0, self.p_final, self.bounds_final) = solve_from_starts(
            starts, solve_one, self.config.solver.restart_physics, self.attempts,
            min_solves=0 if pinned else n_always, workers=start_workers(self.config.solver),
            abandon=self.config.solver.abandon_hopeless, resume=resume)
        self.z = out.z
        return out

    def sampled_starts(self) -> list:
        """The sampler's starts (smc2d.SMCResult): of ``solver.sampler_runs`` runs (seeds
        solver.sampler_seed, +1, ...) the ``solver.sampler_starts`` of highest likelihood
        (smc.best_lineages), or [] where the sampler does not apply (off, pose
        observations, or no fingertip data)."""
        cfg = self.config.solver
        n = int(cfg.sampler_particles)
        if n < 2 or any(r.pose_obs is not None for r in self.runs) or not any(r.n_fingers for r in self.runs):
            return []
        runs = map_in_processes(lambda k: smc_start(self.runs, self.scales.L, self.scales.m0,
                                                    SMCSettings(particles=n, seed=int(cfg.sampler_seed) + k)),
                                int(cfg.sampler_runs), start_workers(cfg))  # independent runs, seeded
        return best_lineages(runs, int(cfg.sampler_starts))

    def sampler_z(self, sampled) -> np.ndarray:
        """Scaled z0 from the sampler's best hypothesis: its box as the starting shape
        (the shape's own initial(w, h)), its mass (held at the prior without a force
        stream), frictions and trajectories; impulses that hold the object up
        (initial.initial_guess)."""
        pr, sc = self.problem, self.scales
        self.s0 = np.asarray(self.shape.initial(sampled.extents[0] / sc.L, sampled.extents[1] / sc.L), float)
        z = initial_guess(pr, self.runs, sc, self.s0, trajectories=sampled.poses)
        ns = pr.n_shape
        log_mass = float(np.clip(np.log(sampled.mass / sc.m0), *LOG_MASS_BOUNDS)) if self.has_force else 0.0
        z[ns:ns + 4] = [log_mass, 0.0, *np.clip([sampled.mu_ground, sampled.mu_finger], *FRICTION_BOUNDS)]
        z[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(pr.phys_sx(z[: pr.n_theta], sc.L, sc.m0)).reshape(-1)
        return self.with_pins(z)

    def fit_quality(self, z):
        """The goodness-of-fit test of the fit at z (fitquality.goodness_of_fit)."""
        return goodness_of_fit([r.residuals for r in self.run_estimates(z)], self.runs, self.problem.K,
                               weights=self.config.to_dict().get("weights", {}))

    def physics_per_sample(self, z) -> float:
        """Objective units per sample of the physics terms (:data:`PHYSICS_TERMS`) at z
        with the final stage's parameters: how far a fit violates its own model."""
        t, _ = self.problem.term_fun(z, self.p_final)
        t = dict(zip(TERMS, np.asarray(t, float).ravel()))
        return sum(t[k] for k in PHYSICS_TERMS) / sum(st.T for st in self.structures)

    # --------------------------------------------------------------------------------
    # what a fit gives

    def physical(self, z):
        """(vertices (K, 2) m, mass kg, inertia kg·m², mu_g, mu_f)."""
        V, mass, inertia, mu_g, mu_f, _ = self.problem.phys_fun(z, self.p_final)
        return (np.array(V), float(mass), float(inertia), float(mu_g), float(mu_f))

    def effect_params(self, z) -> dict:
        """{estimate /params name: physical value} of the effect parameters at z."""
        pr = self.problem
        a = pr.n_shape + len(PHYS_NAMES)
        u = pr.effect_values(np.asarray(z, float), a)
        sc = self.scales
        mu_g = float(np.asarray(z, float)[pr.n_shape + 2])
        out = {}
        for e in pr.effect_objects:
            out.update(e.report(u[e.name], sc, pr.K, mu_g))
        return out

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
        """z with the effects' motion-set states (e.g. restitution's impact memory)
        following their laws along z's trajectories under the parameter vector p."""
        for i in range(len(self.structures)):
            g, D = self._run_data(i, p)
            z = self.problem.settle_states(z, i, D, g)
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
        run = self.runs[i]
        Lam = self.scales.m0 * self.scales.g * run.dt
        K = self.problem.K
        res = self._stage_outputs(z, i)
        imp = {
            "ground_normal": np.vstack([np.zeros((1, K)), LG[:K].T * Lam]),
            "ground_tangent": np.vstack([np.zeros((1, K)), LG[K:].T * Lam]),
        }
        fi = np.asarray(res["imp_finger"]).T  # (T-1, 2F)
        for f in range(self.structures[i].F):
            imp[f"finger_{f}"] = np.vstack([np.zeros((1, 2)), fi[:, 2 * f: 2 * f + 2]])
        return Q.T * scale, Vv.T * scale, imp

    def run_estimates(self, z) -> list:
        """RunEstimate of every run at z (trajectory, impulses, per-sample residuals)."""
        out = []
        for i, run in enumerate(self.runs):
            pose, vel, imp = self.trajectories(z, i)
            src = run.filename or ""
            out.append(RunEstimate(pose=pose, velocity=vel, impulses=imp, residuals=self.per_sample_residuals(z, i),
                                   source_file=src, source_sha256=run_sha256(run)))
        return out

    def result(self, out: SolveOutcome, wall_time: float, information=True, held=None, notes=(),
               penalty_shift=True) -> Estimate:
        """The Estimate of the fit ``out`` (result.assemble): with ``information`` the
        observed information (and, with ``penalty_shift``, the Occam term's shift), and the
        identifiability policy; ``held`` (default: every parameter pinned) reports nothing
        as identifiable (a held-out fit)."""
        pr, z = self.problem, out.z
        V, mass, inertia, mu_g, mu_f = self.physical(z)
        params = {"mass": mass, "inertia": inertia, "friction_ground": mu_g, "friction_finger": mu_f}
        params.update(self.effect_params(z))
        held_all = self.pinned_theta is not None and self.pin == "all" if held is None else bool(held)
        info = None
        if information and not (self.pinned_theta is not None and self.pin == "all"):
            info = self.information(z, penalty_shift=penalty_shift)
        facts = FitFacts(
            has_force=self.has_force, has_fingers=any(r.n_fingers for r in self.runs),
            at_bound={"mass": ended_at_bound(np.log(mass / self.scales.m0), LOG_MASS_BOUNDS),
                      "friction_ground": ended_at_bound(mu_g, FRICTION_BOUNDS),
                      "friction_finger": ended_at_bound(mu_f, FRICTION_BOUNDS)},
            effect_sigma=self.effect_prior_sigmas(z), effects=pr.effects, held=held_all,
            shape_seen=shape_seen(self.runs), shape_names=tuple(information_names_2d(pr)[: pr.n_shape]),
            shape_at_bound=shape_params_at_bound(self.shape, np.asarray(z, float)[: pr.n_shape],
                                                 self.size_bound / self.scales.L,
                                                 names=information_names_2d(pr)[: pr.n_shape]))
        return assemble(2, self.shape.name, V, params, self.run_estimates(z), out, wall_time, info, facts,
                        self.config.to_dict(), "implicit",
                        extra={"length_scale": self.scales.L, "mass_scale": self.scales.m0, "gravity": self.scales.g},
                        attempts=self.attempts, notes=notes, data=self.runs, sensor_noise=self.sensor_noise,
                        vertex_jacobian=vertex_jacobian(lambda p_: numeric_vertices(self.shape, p_ / self.scales.L,
                                                                                    self.scales.L),
                                                        np.asarray(z[: pr.n_shape], float) * self.scales.L))

    def information(self, z, penalty_shift=False):
        """The observed information of the fit at z (uncertainty.observed_information_2d)
        with the final stage's parameters (the sensors' noise levels as the data show
        them where larger: sensor_noise.judged_params) and bounds."""
        bounds = self.bounds_final if self.bounds_final is not None else self.variable_bounds(z)
        return observed_information_2d(self.problem, z, judged_params(self), *bounds, self.scales, self.physical(z)[1],
                                       penalty_shift=penalty_shift)

    def effect_prior_sigmas(self, z) -> dict:
        """{information row name: the effect parameter's prior sigma, physical units}."""
        pr = self.problem
        a = pr.n_shape + len(PHYS_NAMES)
        out = {}
        for j, (e, p) in enumerate(pr.effect_params):
            _, sigma = e.prior(p, self.config, self.scales.L)
            out[e.info_name(p)] = float(sigma) / e.info_factor(p, float(z[a + j]), self.scales)
        return out


# ------------------------------------------------------------------------------------
# starting from an earlier estimate


def core_theta_of(problem, scales: Scales, estimate: Estimate, what: str = "the estimate") -> np.ndarray:
    """Scaled theta before the effect block, [shape s, log(m/m0), log(I/I_uniform),
    mu_ground, mu_finger], of a 2-D estimate's vertices and parameters (the inverse of the
    problem's theta -> physical map); a TacestError naming ``what`` when the estimate
    does not fit the problem's shape or lacks a parameter."""
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


def theta_of(est: ImplicitEstimator, estimate: Estimate, what: str = "the estimate",
             missing_effects_at_zero: bool = False) -> np.ndarray:
    """Scaled theta of ``est``'s problem from an estimate's vertices and parameters, the
    shape clipped to the estimator's bounds.  Effect parameters the estimate lacks are a
    TacestError, or, with ``missing_effects_at_zero`` (a plain fit warm-starting an
    augmented model), start at "no effect" (the prior centres)."""
    pr, sc = est.problem, est.scales
    core = core_theta_of(pr, sc, estimate, what)
    lo, hi = est.shape.bounds(est.size_bound / sc.L)
    core[: pr.n_shape] = np.clip(core[: pr.n_shape], lo, hi)
    mu_g = float(estimate.params["friction_ground"])
    eff = []
    for e in pr.effect_objects:
        pars = e.parameters(pr.K, 2)
        try:
            u = e.scaled(estimate.params, sc, pr.K, mu_g, 2)
        except KeyError as exc:
            if missing_effects_at_zero:
                u = {p.name: p.centre for p in pars}
            else:
                raise TacestError(f"{what} has no parameter {exc.args[0]!r} (its model: effect {e.name} "
                                  "missing)") from None
        except ValueError as exc:
            raise TacestError(f"{what}: {exc}") from None
        eff += [u[p.name] for p in pars]
    theta = np.concatenate([core, eff])
    if not np.all(np.isfinite(theta)):
        raise TacestError(f"{what} has non-finite parameters")
    return theta


def matching_runs(runs: list, estimate: Estimate) -> list:
    """Per run, the estimate's RunEstimate of the same source file (or of the same
    position when the lists have equal lengths) and length, or None."""
    out = []
    for i, run in enumerate(runs):
        cands = [r for r in estimate.runs if run.filename and r.source_file == run.filename]
        if not cands and len(estimate.runs) == len(runs):
            cands = [estimate.runs[i]]
        cands = [r for r in cands if np.asarray(r.pose).shape[0] == run.n_samples]
        out.append(cands[0] if cands else None)
    return out


def previous_start_2d(est: ImplicitEstimator, previous: Estimate, before: list) -> np.ndarray:
    """Scaled z0 of a start from an earlier estimate ``previous`` of the same object from
    the first samples of ``est``'s runs (a closed loop's last step, before its newest
    poke): its parameters (:func:`theta_of`; effects it lacks at "no effect") and its
    trajectories ``before`` (checked: data.previous_trajectories), each continued over
    the run's newer samples by the push tracker from its last pose
    (initial.continued_trajectory)."""
    pr, sc = est.problem, est.scales
    theta = theta_of(est, previous, "the earlier estimate", missing_effects_at_zero=True)
    V = numeric_vertices(pr.shape, theta[: pr.n_shape], sc.L)
    trajectories = [continued_trajectory(run, V, P) for run, P in zip(est.runs, before)]
    z = initial_guess(pr, est.runs, sc, theta[: pr.n_shape], trajectories=trajectories)
    z[: pr.n_theta] = theta
    z[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(pr.phys_sx(theta, sc.L, sc.m0)).reshape(-1)
    return est.with_pins(z)


def warm_start(est: ImplicitEstimator, warm: Estimate, warm_runs: list = None) -> np.ndarray:
    """Scaled z0 from an earlier estimate: its parameters (effects it lacks at "no
    effect") and, for every run with a warm RunEstimate of the same length (``warm_runs``
    by position, default :func:`matching_runs`), its trajectory and impulses (off-contact
    finger impulses 0; velocities re-derived from the poses so that eq. D2 holds,
    whatever dt the warm trajectory had); the estimator's own start for the others.  The
    pins of ``est`` are applied."""
    pr, sc = est.problem, est.scales
    theta = theta_of(est, warm, "the warm estimate", missing_effects_at_zero=True)
    z = initial_guess(pr, est.runs, sc, theta[: pr.n_shape])
    z[: pr.n_theta] = theta
    z[pr.phys_offset: pr.phys_offset + pr.n_phys] = np.asarray(pr.phys_sx(theta, sc.L, sc.m0)).reshape(-1)
    scale = np.array([sc.L, sc.L, 1.0])
    warm_runs = matching_runs(est.runs, warm) if warm_runs is None else warm_runs
    for i, (run, wr) in enumerate(zip(est.runs, warm_runs)):
        if wr is None or np.asarray(wr.pose).shape[0] != run.n_samples:
            continue
        Lam = sc.m0 * sc.g * run.dt
        Q = (np.asarray(wr.pose, float)[:, :3] / scale).T
        Vv = (np.asarray(wr.velocity, float)[:, :3] / scale).T
        Vv[:, 1:] = np.diff(Q, axis=1) / run.dt
        kw = {"Q": Q, "V": Vv}
        _, _, LG0, LF0 = pr.run_blocks(z, i)
        K = pr.K
        gn = wr.impulses.get("ground_normal")
        if gn is not None and np.asarray(gn).shape == (run.n_samples, K):
            LG = LG0.copy()
            LG[:K] = np.maximum(np.asarray(gn, float)[1:] / Lam, 0.0).T
            gt = wr.impulses.get("ground_tangent")
            if gt is not None and np.asarray(gt).shape == (run.n_samples, K):
                LG[K: 2 * K] = (np.asarray(gt, float)[1:] / Lam).T
            kw["LG"] = LG
        F = run.n_fingers
        if F and all(np.shape(wr.impulses.get(f"finger_{f}", ())) == (run.n_samples, 2) for f in range(F)):
            LF = np.concatenate([np.asarray(wr.impulses[f"finger_{f}"], float)[1:] for f in range(F)], axis=1)
            LF = LF * np.repeat(touching(run)[1:], 2, axis=1)  # off-contact finger impulses are pinned at 0
            kw["LF"] = (LF / Lam).T
        pr.set_run_blocks(z, i, **kw)
    return est.with_pins(z)


def estimate_2d(runs: list[Run], shape_spec: str = "box", config: EstimatorConfig | None = None, effects=(),
                fixed: Estimate | None = None, refit_shape: bool = False, previous: Estimate | None = None) -> Estimate:
    """Estimate one object's parameters and each 2-D run's trajectory.

    effects : effect names modelled as extra parameters (tacest.model.registry;
        docs/diagnosis.md gives each augmentation's equations); their values appear in
        ``Estimate.params`` as ``effect.parameter`` and in the information matrix;
    fixed : an Estimate whose parameters (shape, mass, inertia, frictions and the effect
        parameters of ``effects``) are held fixed: only trajectories and impulses are
        fitted (held-out evaluation); its trajectories start the runs it estimated;
    refit_shape : with ``fixed``, hold everything but the shape, which is refitted from
        the fixed estimate's (a held-out piece may touch faces the fixed fit never saw);
    previous : an earlier estimate of the first samples of the same runs (a closed
        loop's last step): one more start, solved first and compared by objective
        (:func:`previous_start_2d`).
    """
    t_start = time.perf_counter()
    est = ImplicitEstimator(runs, shape_spec, config, effects=effects, previous=previous)
    log.info(f"built NLP: {est.problem.n_z} variables, {est.problem.g.shape[0]} constraints "
             f"({est.build_time:.1f} s)" + (f", effects: {', '.join(est.problem.effects)}" if effects else ""))
    if fixed is None:
        out = est.solve()
        return est.result(out, time.perf_counter() - t_start)
    # held fixed: one staged solve from the fixed estimate's shape and trajectories
    est.pinned_theta = theta_of(est, fixed, "the fixed estimate")
    est.pin = "physics" if refit_shape else "all"
    est.s0 = est.pinned_theta[: est.problem.n_shape].copy()
    out = est.solve_from(warm_start(est, fixed))
    return est.result(out, time.perf_counter() - t_start, information=False, held=True)

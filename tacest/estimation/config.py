"""Typed estimator settings, read from a TOML file (``tacest/configs/estimate.toml``,
shipped with the package and printed by ``tacest config --defaults``, shows every key
with its default and meaning).  Unknown keys are an error; the resolved settings are
written into every estimate file (attr ``config``).

The settings are frozen and validated where they are built (each section's
``__post_init__``): a configuration that exists is a valid one.  Change one with
:meth:`EstimatorConfig.updated` (a new, validated configuration).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tacest.errors import TacestError


@dataclass(frozen=True)
class Noise:
    """Noise levels that whiten the residuals (one sigma)."""

    force: float = 0.05  #: N, measured finger force
    normal: float = 0.05  #: rad, measured contact normal
    contact_gap: float = 5e-4  #: m, finger–object gap while the contact flag is 1
    process: float = 0.05  #: dynamics residual: velocity-change noise per sample, as a fraction of g·dt
    penetration: float = 5e-4  #: m, tolerated ground penetration
    rest: float = 1e-3  #: m/s, velocity at t = 0 (the object starts at rest)
    #: complementarity violation lambda_n·psi(phi), in units of m·g·dt (a vertex off the
    #: ground carrying 5 % of the weight is one sigma)
    complementarity: float = 0.05
    #: dissipation shortfall at the fingertips, in units of m·g·dt × (object lengths
    #: per second); loose because the fingertip's slip comes from filtered positions
    dissipation: float = 0.2
    #: dissipation shortfall at the ground vertices, in the same units relative to the
    #: object's weight: sliding at 0.5 object lengths per second, friction 10 % off the
    #: cone's limit on a vertex carrying half the weight (mu 0.5) is 0.6 sigma
    dissipation_ground: float = 0.02
    #: m, no action at a distance (2-D): above this height a vertex's ground impulse costs
    #: complementarity in proportion to the height over it, on top of the saturating
    #: lambda_n·psi(phi); 0 (the default) leaves the saturating law alone
    complementarity_reach: float = 0.0
    #: force, normal and contact_gap at the levels the runs' own readings show where those
    #: are larger: the fit whitens by them (touch alone) or is judged by them (pose
    #: observed: goodness-of-fit test, information, stds) (tacest/estimation/
    #: sensor_noise.py; the estimate's attr ``sensor_noise``); false: the levels above
    from_data: bool = True

    def __post_init__(self):
        _positive(self, "noise", nonnegative=("complementarity_reach",))


@dataclass(frozen=True)
class Weights:
    """Multipliers of the whitened loss terms (1 = trust the noise model as is)."""

    force: float = 1.0
    normal: float = 1.0
    contact: float = 1.0
    pose: float = 1.0
    dynamics: float = 1.0
    penetration: float = 1.0
    complementarity: float = 1.0
    dissipation: float = 1.0
    cone: float = 1.0  #: fingertip friction cone, a smooth penalty whitened like complementarity
    occam: float = 1.0  #: Occam term of pose-observed trajectories (problem.pose_occam; 1 = as derived, 0 drops it)


@dataclass(frozen=True)
class Prior:
    """Weak priors; they decide only what the data cannot."""

    mass: float = 0.5  #: kg, median of a log-normal prior
    mass_log_sigma: float = 1.5  #: sigma of log(mass)
    friction: float = 0.5  #: prior median (log-normal) or mean (normal) of both friction coefficients
    friction_sigma: float = 1.0  #: sigma of the normal friction prior (used where friction_log_sigma = 0)
    #: sigma of log(mu) of the log-normal friction prior (0: the normal prior of
    #: friction_sigma instead); tacest.model.priors
    friction_log_sigma: float = 0.7
    inertia_log_sigma: float = 0.3  #: sigma of log(I / I_uniform_density)
    #: [low, high]: the friction coefficients (ground and fingertip) a fit may end at and
    #: still be called consistent; a fit outside is marked (fit_quality.implausible: a
    #: wrong basin, such as a light and grippy object or a frictionless fingertip a wrong
    #: shape drifts on; docs/estimation.md, "Goodness of fit").  [0, inf]: no check
    friction_plausible: tuple = (0.02, 1.8)
    size: float = 0.1  #: m, starting extent when the run has no /prior size hint
    size_bound: float = 0.5  #: m, largest extent when the run has no /prior size_bound
    shape_sigma: float = 1.0  #: weak pull of the shape toward its start, in units of L

    def __post_init__(self):
        _positive(self, "prior", nonnegative=("friction", "friction_log_sigma"))
        if self.friction_log_sigma > 0 and not self.friction > 0:
            raise _InvalidSetting(f"prior.friction: must be > 0 with a log-normal prior (friction_log_sigma > 0), "
                                  f"got {self.friction!r}")
        band = self.friction_plausible
        if not (isinstance(band, (list, tuple)) and len(band) == 2
                and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in band)
                and 0 <= band[0] < band[1]):
            raise _InvalidSetting(f"prior.friction_plausible: expected [low, high] with 0 <= low < high, got {band!r}")
        object.__setattr__(self, "friction_plausible", (float(band[0]), float(band[1])))


@dataclass(frozen=True)
class Solver:
    """IPOPT settings and the complementarity homotopy."""

    linear_solver: str = "mumps"
    #: Hessian model per stage: "gauss-newton" (J_rᵀ J_r for the squared terms: positive
    #: semi-definite, robust far from the solution), "exact" (full second derivatives),
    #: or "gauss-newton-then-exact" (exact in the last homotopy stage only)
    hessian: str = "gauss-newton"
    #: Levenberg–Marquardt ridge added to the Hessian model (scaled units); keeps
    #: Gauss–Newton steps local where the data leave directions weakly determined.  3.0
    #: (was 0.05): on 4 gentle and 4 dynamic box recordings the median Chamfer went from
    #: 4.7 / 2.2 mm to 0.8 / 1.9 mm and the wall time from 1.2 / 1.9 to 1.0 / 1.0 x the
    #: recording (docs/estimation.md, "Dynamic pokes"): small ridges let the first steps
    #: jump across the mass-friction-width valley to its far end
    hessian_ridge: float = 3.0
    #: the ridge of fits with pose observations (motion capture; tosses): their start is
    #: the observed trajectory, and 3.0 damped their final steps enough to stop 7 % short
    #: on a toss's spin (tests/test_estimator.py, the motion-capture tosses)
    hessian_ridge_observed: float = 0.05
    tol: float = 1e-5  #: IPOPT's (scaled) KKT tolerance
    #: IPOPT's barrier parameter (mu_init, monotone strategy; scaled objective units).
    #: The scaled KKT error of these fits stays above 10 mu, so IPOPT never lowers it:
    #: it is the barrier every solve holds.  A small one keeps the contact impulses at
    #: their bound lambda_n >= 0, but each Newton step that turns contacts on or off is
    #: then cut short by the fraction-to-the-boundary rule.  1e-4 was measured on the
    #: held-out polygons and not kept: other basins, no faster (docs/estimation.md,
    #: "Where a polygon fit's time goes")
    barrier: float = 1e-5
    #: IPOPT's acceptable tolerance (scaled KKT error), with the other acceptable criteria
    #: of estimation/solver.py (objective changing by < 1e-3 of itself for 5 iterations,
    #: constraints to 1e-4).  On polygons the final iterations crawl with line-search
    #: steps of 1e-2..1e-4 while the objective changes by < 1e-3 of itself and the scaled
    #: dual infeasibility wanders between 5 and 20: 10 turned such converged fits into
    #: iteration-limit failures
    acceptable_tol: float = 100.0
    max_iter: int = 400  #: for the final stage
    stage_max_iter: int = 60  #: for the intermediate stages (they only prepare the next)
    max_cpu_time: float = 600.0  #: s, per stage
    #: relaxation stages [epsilon, complementarity multiplier, dynamics multiplier]:
    #: epsilon smooths max(phi, 0) (in contact-gap sigmas) and |slip|; the last stage is
    #: the model as configured.  (Weakening the dynamics early lets the object float
    #: off: touches alone do not pin shape and trajectory apart.)
    homotopy: tuple = ((1.0, 0.1, 1.0), (0.3, 1.0, 1.0))
    print_every: int = 10  #: iterations between progress lines
    #: further starting shapes tried when a fit fails or violates its own physics by more
    #: than restart_physics (estimator.ImplicitEstimator.solve)
    restarts: int = 2
    #: objective units per sample of the physics terms (dynamics, penetration,
    #: complementarity, dissipation, cone) above which a fit is a local minimum worth a
    #: restart.  Closed-loop fits of boxes that place the shape within a few mm hold
    #: 0.001-0.03 per sample; fits that float or sink the object to follow the touches of
    #: a wrong shape (Chamfer 10-30 mm) 0.2-1.1
    restart_physics: float = 0.1
    #: hypotheses of the sequential Monte Carlo start (estimation/smc2d.py) of 2-D runs
    #: without pose observations: the first start follows the object through its tips and
    #: topples; 0 turns it off (push-tracked starts only)
    sampler_particles: int = 256
    #: seed of the sampler's random draws (the same runs and seed give the same start)
    sampler_seed: int = 0
    #: independent sampler runs (seeds sampler_seed, sampler_seed + 1, ...)
    sampler_runs: int = 2
    #: of those runs' lineages, how many (highest likelihood first, distinct boxes:
    #: smc.best_lineages) start an NLP solve, all solved, the lowest objective kept: one
    #: run's best lineage can lead the NLP into a local minimum whose fit still looks
    #: consistent (docs/estimation.md, "Dynamic pokes")
    sampler_starts: int = 2
    #: processes that solve the compared starts at once (the sampler's, an earlier
    #: estimate's and, in 3-D without pose observations, every push-tracked one), and the
    #: samplers' seeded runs: forked copies of the process with its built NLP
    #: (solver.solve_from_starts, tacest.parallel.fork_map).  0: one per core this
    #: process may use, at most one per job; 1: one after another (so also, whatever
    #: this says, off Linux, inside a daemonic process such as a Dask worker, beside
    #: other threads, and with an OpenMP linear solver).  The fits are the same either
    #: way; the restarts after them run one after another
    start_workers: int = 0
    #: stop a start (2-D and 3-D) whose final stage stays far above the best fit
    #: finished so far, in this process or one beside it (after 20 iterations 10x its
    #: objective, after 30 5x, after 100 3x: solver.ABANDON_RULE); its fit could not be
    #: kept.  false: every start runs to its end
    abandon_hopeless: bool = True
    #: stop a 2-D start's final stage that has stalled (from iteration 150 on, its lowest
    #: objective fell by less than 1 % over the last 100 iterations: solver.STALL_RULE)
    #: and set it aside as if it had used up its iteration budget (it competes by its
    #: objective and never ends the search; kept at the search's end, it is resumed from
    #: its last iterate to convergence or max_iter).  false: it runs to max_iter
    stop_stalled: bool = True
    #: s: runs sampled at a period of at most half this are fitted on blocks of
    #: samples lasting at most this period and their trajectories brought back to every sample
    #: (tacest/io/resample.py; ``tacest estimate`` and what is built on it, not the
    #: diagnosis); 0: every run at its own rate
    sample_period: float = 0.01

    def __post_init__(self):
        if not (isinstance(self.sample_period, (int, float)) and not isinstance(self.sample_period, bool)
                and math.isfinite(self.sample_period) and self.sample_period >= 0):
            raise _InvalidSetting(f"solver.sample_period must be a number of seconds >= 0, got {self.sample_period!r}")
        if isinstance(self.start_workers, bool) or not isinstance(self.start_workers, int) \
                or self.start_workers < 0:
            raise _InvalidSetting(f"solver.start_workers must be an integer >= 0, got {self.start_workers!r}")
        _check_stages(self, "solver", "")
        _check_sampler(self, "solver", "sampler_runs")
        _check_sampler_starts(self, "solver")
        _check_restarts(self, "solver")
        if isinstance(self.barrier, bool) or not isinstance(self.barrier, (int, float)) \
                or not (0 < self.barrier < 1):
            raise _InvalidSetting(f"solver.barrier must be a number in (0, 1), got {self.barrier!r}")
        if self.linear_solver not in LINEAR_SOLVERS:
            raise _InvalidSetting(f"solver.linear_solver: unknown {self.linear_solver!r}; one of {', '.join(LINEAR_SOLVERS)}")


@dataclass(frozen=True)
class Solver3D:
    """Stages of the 3-D estimator (estimator3d.py); IPOPT's other settings are [solver]'s."""

    #: Hessian model, as solver.hessian; Gauss–Newton converges in ~15-30 iterations on
    #: pose-observed tosses, the exact Hessian takes ~8x longer for the same estimates
    hessian: str = "gauss-newton"
    #: relaxation stages [epsilon, complementarity multiplier, dynamics multiplier], as
    #: solver.homotopy; pose observations and a data-driven starting scale give a start
    #: close enough for one stage at the final model
    homotopy: tuple = ((0.3, 1.0, 1.0),)
    #: Levenberg–Marquardt ridge of the Hessian model (scaled units), as
    #: solver.hessian_ridge; smaller ridges let the first Gauss–Newton steps jump to a
    #: poorer local minimum of the contact assignment (3 % shape error on the tests' tosses)
    hessian_ridge: float = 1.0
    #: IPOPT's acceptable tolerance (scaled KKT error), as solver.acceptable_tol
    acceptable_tol: float = 1.0
    #: augmentation ``ground_offset``: sigma (m) of a zero-mean prior on the height of the
    #: ground plane above the runs' /scene ground_height, estimated with the object; 0 holds
    #: the ground where the runs put it (docs/estimation3d.md)
    ground_offset_sigma: float = 0.0
    #: augmentation ``edge_radius`` (box only): sigma (m) of a half-normal prior at 0 on the
    #: radius of the box's rounded edges and corners; 0 keeps the edges sharp.  On by
    #: default: the real tossed cube rocks on ~2 mm rounded edges, and a sharp box then
    #: comes out 2 % small (docs/estimation3d.md); a sharp object gets a radius near 0
    edge_radius_sigma: float = 0.005
    #: runs without pose observations (finger pokes): relaxation stages as homotopy.  Two
    #: stages at the final model, the first Gauss–Newton (solver.stage_max_iter), the
    #: second with hessian_no_pose: Gauss–Newton alone creeps along a flat valley (mass
    #: against ground friction, untouched extents) and stops at max_iter (simulated pokes,
    #: seed 3: objective 199 -> 193 over 340 iterations); the exact Hessian then converges
    #: in ~70 (docs/estimation3d.md)
    homotopy_no_pose: tuple = ((0.3, 1.0, 1.0), (0.3, 1.0, 1.0))
    #: runs without pose observations: Hessian model, as hessian
    hessian_no_pose: str = "gauss-newton-then-exact"
    #: runs without pose observations: IPOPT iterations of the final stage (solver.max_iter
    #: for the others).  The exact-Hessian stage creeps along the flat directions an
    #: untouched extent leaves: a toppled box's fit from the sampled start took 420
    #: iterations (objective 75.0 -> 64.7, the last 100 within 0.01 %) and ended 1.9 mm
    #: from the truth.  A start that uses up this budget competes by its last iterate's
    #: objective (solver.solve_from_starts), so the budget bounds the time a creeping
    #: start costs: at 800 a closed loop's sampler start crept 800 iterations (~400 s)
    #: to objective 391 beside the kept 97 (docs/estimation3d.md, "Sampled starts")
    max_iter_no_pose: int = 300
    #: runs without pose observations: IPOPT's acceptable tolerance (scaled KKT error) of
    #: every stage, as solver.acceptable_tol (the 2-D one).  At 1.0 the exact-Hessian stage
    #: crept for hundreds of iterations with a dual infeasibility of 7-50 and 5-8
    #: backtracks per step (a contact-smoothed loss the Newton model overshoots): 187 s
    #: for a 5-poke, 9 s recording, objective 53.9 -> 51.8, Chamfer 0.95 mm; at 100 it
    #: stops once the objective changes by < 1e-3 of itself for 5 iterations: 17 s,
    #: objective 54.3, 1.15 mm (docs/estimation3d.md, "Speed").  The diagnosis keeps
    #: acceptable_tol (it compares objectives to a few units)
    acceptable_tol_no_pose: float = 100.0
    #: runs without pose observations: solve from every compared start (the sampler's
    #: and compared_push_tracked push-tracked ones; the others are restarts) and keep the
    #: lowest objective, instead of stopping at the first fit that passes restart_physics.  With the acceptable level
    #: above, a wrong basin converges fast and passes (a 23° dynamic recording: 36 mm,
    #: objective 105.3, marked consistent); the sampler's start, solved too, reaches
    #: 104.5 and 9.4 mm, and the fits within the likelihood-ratio bound widen the std
    #: (docs/estimation3d.md, "Speed")
    compare_starts: bool = True
    #: with compare_starts: how many of the push-tracked starts (best first) are compared
    #: beside the sampler's; the further ones, and the resting start, are restarts only.
    #: Over 30 benchmark recordings the second push-tracked start, compared, was kept on
    #: 4 (3 gentle, 1 dynamic) and moved their body errors both ways (6.5 -> 4.6, 4.6 ->
    #: 0.6, 0.3 -> 4.7, 14.1 -> 9.3 mm without it), for one more solve on every
    #: recording (docs/estimation3d.md, "Compared starts")
    compared_push_tracked: int = 1
    #: runs without pose observations only: further push-tracked (or resting) starts tried
    #: when a fit fails or violates its own physics by more than restart_physics
    #: (initial3d.py, estimator3d.Estimator3D.solve), besides the sampler's start (one
    #: more, sampler_particles); pose-observed runs solve once from their poses
    restarts: int = 2
    #: objective units per sample of the physics terms (dynamics, penetration,
    #: complementarity, dissipation, cone) above which a 3-D fit without pose observations
    #: is a local minimum worth a restart.  On simulated 6-poke boxes (seeds 0-5) fits
    #: within 0.4-1.2 mm of the body hold 0.047-0.075; fits 2-5 mm off 0.069-0.12, fits
    #: 6-26 mm off 0.12-3.5; the truth 0.054-0.098 (docs/estimation3d.md)
    restart_physics: float = 0.1
    #: hypotheses of the sequential Monte Carlo start (estimation/smc3d.py) of 3-D runs
    #: without pose observations; 0 turns it off (push-tracked starts only)
    sampler_particles: int = 256
    #: seed of the sampler's first run (the same runs and seed give the same start)
    sampler_seed: int = 0
    #: independent sampler runs (seeds sampler_seed, +1, ...); the lineages of highest
    #: likelihood are starts (one run of 256 hypotheses finds a topple's basin on about
    #: one seed in three, and its likelihood is thousands above the others': 3 runs
    #: gave median 16.1 / 7.2 mm on tuning / held-out dynamic recordings, 8 runs 5.5 /
    #: 5.3 mm; docs/estimation3d.md, "Sampled starts")
    sampler_runs: int = 8
    #: of those runs' lineages, how many (highest likelihood first, distinct boxes) are
    #: compared starts
    sampler_starts: int = 1
    #: degrees: a sampled lineage that tilts further than this goes first (the push
    #: tracker never tips the box); a flatter one is the first restart
    sampler_tip_deg: float = 20.0
    #: runs without pose observations, one run of several actions, no earlier estimate
    #: given: build the estimate up action by action, each step started from the last
    #: step's estimate too (as --start-from), the last step the estimate (estimator3d.
    #: grow_horizon).  Off by default: it found basins fresh fits missed on some dynamic
    #: recordings (12.6 -> 1.4 mm) and lost others (9.3 -> 24.9 mm); over six held-out
    #: dynamic recordings the median went 7.9 -> 7.4 mm at 3-5x the wall time, and one
    #: gentle recording 0.67 -> 4.59 mm (docs/estimation3d.md, "Growing horizon")
    growing_horizon: bool = False

    def __post_init__(self):
        _check_sampler(self, "solver3d", "sampler_runs")
        _check_sampler_starts(self, "solver3d")
        if self.compared_push_tracked < 0:
            raise _InvalidSetting(f"solver3d.compared_push_tracked must be >= 0, got {self.compared_push_tracked}")
        if self.max_iter_no_pose < 1:
            raise _InvalidSetting(f"solver3d.max_iter_no_pose must be >= 1, got {self.max_iter_no_pose}")
        for k in ("acceptable_tol", "acceptable_tol_no_pose"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise _InvalidSetting(f"solver3d.{k} must be > 0, got {v!r}")
        if not (np.isfinite(self.sampler_tip_deg) and self.sampler_tip_deg >= 0):
            raise _InvalidSetting(f"solver3d.sampler_tip_deg must be >= 0, got {self.sampler_tip_deg!r}")
        _check_stages(self, "solver3d", "")
        _check_stages(self, "solver3d", "_no_pose")
        _check_restarts(self, "solver3d")
        for k in ("ground_offset_sigma", "edge_radius_sigma"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v >= 0):
                raise _InvalidSetting(f"solver3d.{k} must be >= 0, got {v!r}")


@dataclass(frozen=True)
class EstimatorConfig:
    noise: Noise = field(default_factory=Noise)
    weights: Weights = field(default_factory=Weights)
    prior: Prior = field(default_factory=Prior)
    solver: Solver = field(default_factory=Solver)
    solver3d: Solver3D = field(default_factory=Solver3D)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def with_reach(self, reach: float) -> "EstimatorConfig":
        """A copy with noise.complementarity_reach = ``reach`` (m; 0: off)."""
        return self.updated({"noise": {"complementarity_reach": float(reach)}})

    def updated(self, overrides: dict) -> "EstimatorConfig":
        """A new configuration: this one with ``overrides`` ({section: {key: value}}),
        checked as a TOML file's values are (unknown keys and wrong types are errors)."""
        data = self.to_dict()
        for section, values in overrides.items():
            if not isinstance(values, dict) or section not in data:
                raise TacestError(f"config: unknown section {section!r}")
            data[section].update(values)
        return _build(data, "config")


#: IPOPT linear solvers tacest accepts (MUMPS ships with CasADi; the HSL ones need HSL)
LINEAR_SOLVERS = ("mumps", "spral", "ma27", "ma57", "ma86", "ma97")
#: Hessian models of a staged solve (tacest.estimation.solver.plan_stages)
HESSIAN_CHOICES = ("gauss-newton", "exact", "gauss-newton-then-exact")


def _positive(section, name, nonnegative=()):
    """Every float of a section > 0 (the names in ``nonnegative``: >= 0), finite."""
    for f in dataclasses.fields(section):
        v = getattr(section, f.name)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        ok = v >= 0 if f.name in nonnegative else v > 0
        if not (math.isfinite(v) and ok):
            raise _InvalidSetting(f"{name}.{f.name}: must be {'>= 0' if f.name in nonnegative else '> 0'}, got {v!r}")


def _check_stages(section, name, suffix):
    """Validate and normalise (to a tuple of triples) a section's homotopy{suffix} and
    its hessian{suffix}."""
    hom, hessian = getattr(section, "homotopy" + suffix), getattr(section, "hessian" + suffix)
    if not isinstance(hom, (list, tuple)) or not hom or not all(
            isinstance(st, (list, tuple)) and len(st) == 3
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and x > 0 for x in st) for st in hom):
        raise _InvalidSetting(f"{name}.homotopy{suffix}: expected a list of [epsilon, complementarity, dynamics] "
                          "triples of positive numbers")
    object.__setattr__(section, "homotopy" + suffix, tuple(tuple(float(x) for x in st) for st in hom))
    if hessian not in HESSIAN_CHOICES:
        raise _InvalidSetting(f"{name}.hessian{suffix}: expected gauss-newton, exact or gauss-newton-then-exact, "
                          f"got {hessian!r}")


def _check_sampler(section, name, runs_key):
    """The sampling start's settings of a section: particles 0 (off) or >= 2, seed >= 0,
    and its number of runs (``runs_key``) >= 1."""
    if section.sampler_particles < 0 or section.sampler_particles == 1:
        raise _InvalidSetting(f"{name}.sampler_particles must be 0 (off) or >= 2, got {section.sampler_particles}")
    if section.sampler_seed < 0:
        raise _InvalidSetting(f"{name}.sampler_seed must be >= 0, got {section.sampler_seed}")
    if getattr(section, runs_key) < 1:
        raise _InvalidSetting(f"{name}.{runs_key} must be >= 1, got {getattr(section, runs_key)}")


def _check_sampler_starts(section, name):
    if not 1 <= section.sampler_starts <= section.sampler_runs:
        raise _InvalidSetting(f"{name}.sampler_starts must be within 1..{name}.sampler_runs ({section.sampler_runs}), "
                              f"got {section.sampler_starts}")


def _check_restarts(section, name):
    if section.restarts < 0 or not section.restart_physics > 0:
        raise _InvalidSetting(f"{name}.restarts must be >= 0 and {name}.restart_physics > 0, got "
                          f"{section.restarts} and {section.restart_physics}")


def _fill(cls, data: dict, where: str):
    if not isinstance(data, dict):
        raise TacestError(f"{where}: expected a table")
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise TacestError(f"{where}: unknown key(s) {', '.join(unknown)}; valid: {', '.join(sorted(names))}")
    kwargs = {}
    for k, v in data.items():
        default = getattr(cls(), k)
        if dataclasses.is_dataclass(default):
            kwargs[k] = _fill(type(default), v, f"{where}.{k}")
        elif isinstance(default, bool):
            if not isinstance(v, bool):
                raise TacestError(f"{where}.{k}: expected true or false, got {v!r}")
            kwargs[k] = v
        elif isinstance(default, int) and not isinstance(default, bool):
            if not isinstance(v, int) or isinstance(v, bool):
                raise TacestError(f"{where}.{k}: expected an integer, got {v!r}")
            kwargs[k] = v
        elif isinstance(default, float):
            if not isinstance(v, (int, float)) or isinstance(v, bool):
                raise TacestError(f"{where}.{k}: expected a number, got {v!r}")
            kwargs[k] = float(v)
        else:
            kwargs[k] = v
    return cls(**kwargs)


class _InvalidSetting(TacestError):
    """A section's own check failed (its message names the setting, not the source)."""


def _build(data: dict, source: str) -> "EstimatorConfig":
    """The configuration of ``data`` ({section: {key: value}}); errors name ``source``."""
    try:
        return _fill(EstimatorConfig, data, source)
    except _InvalidSetting as exc:
        raise TacestError(f"{source}: {exc}") from None


def load_config(path=None, overrides: dict | None = None) -> EstimatorConfig:
    """Defaults, updated by the TOML file at ``path`` (if any) and then ``overrides``."""
    data: dict = {}
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise TacestError(f"{p}: no such config file")
        try:
            data = tomllib.loads(p.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise TacestError(f"{p}: not valid TOML ({exc})") from None
    for section, values in (overrides or {}).items():
        data.setdefault(section, {}).update(values)
    return _build(data, str(path) if path else "config")


def solver_structure_key(solver: Solver) -> str:
    """The part of the [solver] settings that a built solver depends on (its cache key):
    all but how many processes solve the starts."""
    import dataclasses

    return repr(dataclasses.replace(solver, start_workers=0))


def start_workers(solver: Solver) -> int:
    """The ``workers`` of the starts' forked solves (tacest.parallel.fork_processes):
    ``solver.start_workers``, or 1 with a linear solver that runs OpenMP threads (a
    forked child of a process that used them can deadlock)."""
    from tacest.parallel import OPENMP_LINEAR_SOLVERS

    return 1 if solver.linear_solver in OPENMP_LINEAR_SOLVERS else int(solver.start_workers)

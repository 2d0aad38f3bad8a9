"""Choose the next poke from an estimate: ``eig``, ``random`` or ``identity``.

- ``eig``: cross-entropy search (tacest.planning.cem) over the action space
  (tacest.planning.actions), per finger, of score(F(a), I_past), where F(a) is the
  expected Fisher information of the predicted poke (tacest.information.expected:
  simulated on the estimated object, Schur complement of the estimator's linearized
  residuals) and I_past the estimate's observed information plus the estimator's prior;
- ``identity``: the same search with the quasi-static identity-Jacobian approximation
  of F (no dynamics in the Jacobian);
- ``random``: a random finger and approach direction (the seeds' baseline); its
  expected-information score is computed and written too, for comparison.

Every method aims at the estimated centroid.  :func:`plan_next` returns a
tacest.io.plan.Plan (candidates, scores, chosen action).

3-D estimates (tacest.information.expected3d) are planned the same way over the 3-D
action space (tacest.planning.actions.ActionSpace3: azimuth, elevation), with the
information of a predicted poke and of the past built by ``information``
(tacest.information.sensitivity: ``schur``, ``identity``, ``diffsim`` or ``marginal``;
default ``marginal``; the ``identity`` method uses ``identity``).  In 2-D every
construction is offered for the candidates (default ``schur``); the past stays the
estimate's observed information (its Schur complement) plus the prior.
"""

from __future__ import annotations

import logging

import json
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from tacest.errors import TacestError
from tacest.estimation.solver import SolverCache
from tacest.information.expected import (PREDICT_SUBSTEPS, ExpectedInformation, ModelState, config_of_estimate,
                                         past_information, predict_poke)
from tacest.information.scores import SCORES, score
from tacest.io.plan import Plan
from tacest.information.sensitivity import INFORMATION_METHODS
from tacest.planning.actions import ACTION_STYLES, action_space_for
from tacest.planning.cem import cem_maximize

log = logging.getLogger(__name__)

METHODS = ("eig", "random", "identity")
#: the information used when ``PlanSettings.information`` is None, per dimension
DEFAULT_INFORMATION = {2: "schur", 3: "marginal"}


@dataclass
class PlanSettings:
    """Planner settings (written to the plan file as JSON attr ``planner``).

    method : eig | random | identity; score : logdet | A | D | E; seed : int;
    iterations, population, elite : CEM per finger (iterations × population
    candidates per finger; elite 0: a third of the population, at least 1); vary : subset of
    ("depth", "speed", "height"); poke_style : gentle | dynamic (tacest.planning.actions:
    dynamic searches speed and aim height, fast pokes that tip and topple); substeps : physics
    substeps per sample of a prediction; noise_samples : average F over this many noisy
    sensor draws (0: the closed form at the noiseless prediction; 2-D only);
    information : schur | identity | diffsim | marginal (tacest.information.sensitivity;
    None: :data:`DEFAULT_INFORMATION` of the estimate's dimension; the ``identity``
    method always uses ``identity``); fingers_per_action : fingers moving together in one
    action (3-D only; tacest.planning.actions.ActionSpace3); workers : processes that
    score a 3-D search's candidates (forked copies of this one,
    tacest.parallel.fork_processes; 0: one per core, 1: this process only; the plan is
    the same for any number).
    """

    method: str = "eig"
    score: str = "logdet"
    seed: int = 0
    iterations: int = 4
    population: int = 12
    elite: int = 0
    vary: tuple = field(default_factory=tuple)
    substeps: int = PREDICT_SUBSTEPS
    noise_samples: int = 0
    information: str | None = None
    poke_style: str = "gentle"
    fingers_per_action: int = 1
    workers: int = 0

    def validate(self) -> "PlanSettings":
        if self.method not in METHODS:
            raise TacestError(f"unknown planning method {self.method!r}: use {', '.join(METHODS)}")
        if self.score not in SCORES:
            raise TacestError(f"unknown score {self.score!r}: use {', '.join(SCORES)}")
        if int(self.seed) < 0:
            raise TacestError(f"--seed must be >= 0, got {self.seed}")
        if not (self.iterations >= 1 and self.population >= 2 and 0 <= self.elite <= self.population):
            raise TacestError("CEM needs iterations >= 1, population >= 2 and 0 <= elite <= population")
        if int(self.substeps) < 1 or int(self.noise_samples) < 0:
            raise TacestError("substeps must be >= 1 and noise_samples >= 0")
        if self.poke_style not in ACTION_STYLES:
            raise TacestError(f"unknown poke style {self.poke_style!r}: use {', '.join(ACTION_STYLES)}")
        if self.information is not None and self.information not in INFORMATION_METHODS:
            raise TacestError(f"unknown information {self.information!r}: use {', '.join(INFORMATION_METHODS)}")
        if int(self.workers) < 0:
            raise TacestError(f"planner workers must be >= 0 (0: one per core), got {self.workers}")
        if int(self.fingers_per_action) < 1:
            raise TacestError(f"--fingers-per-action must be >= 1, got {self.fingers_per_action}")
        if self.method == "identity" and self.information not in (None, "identity"):
            raise TacestError(f"method identity is the identity-Jacobian information; "
                              f"--information {self.information} goes with method eig")
        return self

    def information_for(self, dim: int) -> str:
        """The information construction used for an estimate of ``dim``."""
        if self.method == "identity":
            return "identity"
        return self.information or DEFAULT_INFORMATION[int(dim)]


#: built expected-information models kept per process (least recently used dropped
#: first, tacest.estimation.solver.SolverCache): the key holds the estimate's scales, so
#: every step of a closed loop can build a new one, and an unbounded cache grows with
#: the loop as the solver cache did (docs/parallel.md, "Memory")
INFO_CACHE_LIMIT = 4
_INFO_CACHE = SolverCache(limit=INFO_CACHE_LIMIT)


def expected_information_model(shape_spec: str, n_fingers: int, config, L: float, m0: float) -> ExpectedInformation:
    """The ExpectedInformation of a structure, built once per process and reused."""
    key = (shape_spec, int(n_fingers), json.dumps(config.to_dict(), sort_keys=True), float(L), float(m0))
    return _INFO_CACHE.get(key, lambda: ExpectedInformation(shape_spec, n_fingers, config, L, m0))


@dataclass
class Scorer:
    """score(action) for one estimate: predict, F, scalarize.  Counts evaluations."""

    info: ExpectedInformation
    model: ModelState
    I_past: np.ndarray
    kind: str
    approximation: str = "fisher"
    substeps: int = PREDICT_SUBSTEPS
    noise_samples: int = 0
    noise: tuple = (0.02, 0.02, 1e-4)
    evaluations: int = 0

    def information(self, action) -> np.ndarray:
        """F (n, n) of the poke vector ``action``, physical units."""
        from tacest.information.expected import expected_information

        pred = predict_poke(self.model, action, substeps=self.substeps)
        return expected_information(self.info, self.model, pred, method=self.approximation,
                                    noise_samples=self.noise_samples, noise=self.noise, seed=self.evaluations)

    def __call__(self, action) -> float:
        self.evaluations += 1
        return score(self.information(action), self.I_past, self.kind)


@dataclass
class Scorer3(Scorer):
    """The 3-D Scorer: predict in the MuJoCo world (predict_poke_3d), F by the
    ``approximation`` construction of tacest.information.sensitivity (common random
    numbers ``seed`` for ``marginal``: every candidate sees the same draws)."""

    seed: int = 0

    def information(self, action) -> np.ndarray:
        from tacest.information.expected3d import predict_poke_3d

        pred = predict_poke_3d(self.model, action, substeps=self.substeps)
        return self.info.information(self.model, pred, method=self.approximation, seed=self.seed)

    def many(self, actions, workers: int = 1) -> list:
        """[score(a) for a in actions], by ``workers`` forked copies of this process
        (tacest.parallel.fork_map; each candidate's score does not depend on where or in
        which order it is computed: common random numbers ``seed``)."""
        from tacest.information.expected3d import SETTLE_TIME, settled_world
        from tacest.parallel import forked_map

        settled_world(self.model, self.model.dt / int(self.substeps), SETTLE_TIME)  # once, inherited by the workers
        counted = self.evaluations + len(actions)  # the workers' counts stay in the workers
        out = forked_map(self, actions, workers)
        self.evaluations = counted
        return out


_INFO3_CACHE = SolverCache(limit=INFO_CACHE_LIMIT)


def expected_information_model_3d(shape_spec: str, n_fingers: int, config, effects: tuple, scales):
    """The ExpectedInformation3D of a structure, built once per process and reused."""
    from tacest.information.expected3d import ExpectedInformation3D

    key = (shape_spec, int(n_fingers), json.dumps(config.to_dict(), sort_keys=True), tuple(effects),
           float(scales.L), float(scales.m0), float(scales.g))
    return _INFO3_CACHE.get(key, lambda: ExpectedInformation3D(shape_spec, n_fingers, config, tuple(effects), scales))


def make_scorer_3d(est, runs, settings: PlanSettings) -> Scorer3:
    """The Scorer3 of a 3-D estimate and its runs; I_past by the same construction as
    the candidates' F (tacest.information.expected3d.ExpectedInformation3D.past_information)."""
    from tacest.information.expected3d import ModelState3

    if int(settings.noise_samples) > 0:
        raise TacestError("noise_samples (noisy sensor draws of a prediction) is offered in 2-D only")
    config = config_of_estimate(est)
    model = ModelState3.from_estimate(est, runs, config)
    info = expected_information_model_3d(model.shape.name, model.n_fingers, config, model.effects, model.scales)
    how = settings.information_for(3)
    I_past = info.past_information(est, runs, model, method=how, seed=int(settings.seed))
    return Scorer3(info=info, model=model, I_past=I_past, kind=settings.score, approximation=how,
                   substeps=settings.substeps, seed=int(settings.seed))


def make_scorer(est, runs, settings: PlanSettings) -> Scorer:
    """The Scorer of an estimate (tacest.io.estimate.Estimate) and its runs (2-D or 3-D)."""
    from tacest.estimation.data import choose_scales

    if int(est.dim) == 3:
        return make_scorer_3d(est, runs, settings)
    config = config_of_estimate(est)
    model = ModelState.from_estimate(est, runs)
    scales = choose_scales(runs, config)
    info = expected_information_model(model.shape.name, model.n_fingers, config, scales.L, scales.m0)
    I_past = past_information(est, model, config, scales.L, info.names)
    noise = tuple(float(np.asarray(runs[-1].extra_attrs.get(k, d))) for k, d in
                  (("noise_force", config.noise.force), ("noise_normal", config.noise.normal),
                   ("noise_position", 1e-4)))
    return Scorer(info=info, model=model, I_past=I_past, kind=settings.score,
                  approximation=settings.information_for(2),
                  substeps=settings.substeps, noise_samples=settings.noise_samples, noise=noise)


def plan_next(est, runs, settings: PlanSettings | None = None) -> Plan:
    """The next poke for the object of ``est`` (an Estimate) recorded in ``runs``.

    Returns a Plan: candidates (N, n) action vectors (POKE_NAMES, or in 3-D
    tacest.sim3d.pokes.action_names of settings.fingers_per_action)
    with their scores, the chosen one, method, score, estimate_sha256 and attrs ``planner`` (settings JSON),
    ``wall_time`` (s), ``evaluations``, ``target`` (the estimated centroid, m).
    """
    settings = (settings or PlanSettings()).validate()
    t0 = time.perf_counter()
    scorer = make_scorer(est, runs, settings)
    model = scorer.model
    space = action_space_for(model, settings.poke_style, settings.vary, settings.fingers_per_action)
    target = model.centroid__world
    rng = np.random.default_rng(np.random.SeedSequence([int(settings.seed), 4]))
    cands, scores = [], []
    if settings.method == "random":
        a = space.random_action(rng, target)
        cands.append(a)
        scores.append(scorer(a))
    else:
        lo, hi = space.bounds()
        for f in space.searched_fingers():
            many = None
            if isinstance(scorer, Scorer3):
                many = lambda U: scorer.many([space.action(f, u, target) for u in U], settings.workers)  # noqa: E731
            res = cem_maximize(lambda u: scorer(space.action(f, u, target)), lo, hi, rng,
                               iterations=settings.iterations, population=settings.population,
                               elite=settings.elite or max(1, settings.population // 3), many=many)
            cands += [space.action(f, u, target) for u in res.samples]
            scores += list(res.scores)
            log.info(f"finger {'nearest' if f is None else f}: best {settings.score} {np.max(res.scores):.4g} of "
                     f"{len(res.scores)} candidates")
    cands = np.asarray(cands, float).reshape(-1, len(space.poke_names))
    scores = np.asarray(scores, float)
    if not np.any(np.isfinite(scores)):
        raise TacestError("no candidate poke could be scored (every prediction failed)")
    best = int(np.nanargmax(np.where(np.isfinite(scores), scores, -np.inf)))
    if settings.method == "random":
        best = 0
    scores = np.where(np.isfinite(scores), scores, -1e300)  # a plan file holds no NaN or inf scores
    wall = time.perf_counter() - t0
    sha = ""
    if est.filename:
        from tacest.io.h5util import sha256_file

        sha = sha256_file(est.filename)
    return Plan(chosen=cands[best].copy(), candidates=cands, scores=scores, method=settings.method,
                score=settings.score, estimate_sha256=sha, names=list(space.poke_names), kind="poke",
                extra_attrs={"planner": json.dumps({**asdict(settings), "vary": list(settings.vary),
                                                    "information": settings.information_for(est.dim)}),
                             "wall_time": float(wall), "evaluations": int(scorer.evaluations),
                             "target": np.asarray(target, float)})

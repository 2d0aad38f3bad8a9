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
"""

from __future__ import annotations

import logging

import json
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from tacest.errors import TacestError
from tacest.information.expected import (PREDICT_SUBSTEPS, ExpectedInformation, ModelState, config_of_estimate,
                                         past_information, predict_poke)
from tacest.information.scores import SCORES, score
from tacest.io.plan import POKE_NAMES, Plan
from tacest.planning.actions import ActionSpace
from tacest.planning.cem import cem_maximize

log = logging.getLogger(__name__)

METHODS = ("eig", "random", "identity")


@dataclass
class PlanSettings:
    """Planner settings (written to the plan file as JSON attr ``planner``).

    method : eig | random | identity; score : logdet | A | D | E; seed : int;
    iterations, population, elite : CEM per finger (iterations × population
    candidates per finger; elite 0: a third of the population, at least 1); vary : subset of ("depth", "speed"); substeps : physics
    substeps per sample of a prediction; noise_samples : average F over this many noisy
    sensor draws (0: the closed form at the noiseless prediction).
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
        return self


_INFO_CACHE: dict = {}


def expected_information_model(shape_spec: str, n_fingers: int, config, L: float, m0: float) -> ExpectedInformation:
    """The ExpectedInformation of a structure, built once per process and reused."""
    key = (shape_spec, int(n_fingers), json.dumps(config.to_dict(), sort_keys=True), float(L), float(m0))
    if key not in _INFO_CACHE:
        _INFO_CACHE[key] = ExpectedInformation(shape_spec, n_fingers, config, L, m0)
    return _INFO_CACHE[key]


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
        from tacest.information.expected import expected_information

        pred = predict_poke(self.model, action, substeps=self.substeps)
        return expected_information(self.info, self.model, pred, method=self.approximation,
                                    noise_samples=self.noise_samples, noise=self.noise, seed=self.evaluations)

    def __call__(self, action) -> float:
        self.evaluations += 1
        return score(self.information(action), self.I_past, self.kind)


def make_scorer(est, runs, settings: PlanSettings) -> Scorer:
    """The Scorer of an estimate (tacest.io.estimate.Estimate) and its runs."""
    from tacest.estimation.data import choose_scales

    config = config_of_estimate(est)
    model = ModelState.from_estimate(est, runs)
    scales = choose_scales(runs, config)
    info = expected_information_model(model.shape.name, model.n_fingers, config, scales.L, scales.m0)
    I_past = past_information(est, model, config, scales.L, info.names)
    noise = tuple(float(np.asarray(runs[-1].extra_attrs.get(k, d))) for k, d in
                  (("noise_force", config.noise.force), ("noise_normal", config.noise.normal),
                   ("noise_position", 1e-4)))
    return Scorer(info=info, model=model, I_past=I_past, kind=settings.score,
                  approximation="identity" if settings.method == "identity" else "fisher",
                  substeps=settings.substeps, noise_samples=settings.noise_samples, noise=noise)


def plan_next(est, runs, settings: PlanSettings | None = None) -> Plan:
    """The next poke for the object of ``est`` (an Estimate) recorded in ``runs``.

    Returns a Plan: candidates (N, 6) POKE_NAMES vectors with their scores, the chosen
    one, method, score, estimate_sha256 and attrs ``planner`` (settings JSON),
    ``wall_time`` (s), ``evaluations``, ``target`` (the estimated centroid, m).
    """
    settings = (settings or PlanSettings()).validate()
    t0 = time.perf_counter()
    scorer = make_scorer(est, runs, settings)
    model = scorer.model
    space = ActionSpace(n_fingers=model.n_fingers, vary=tuple(settings.vary))
    target = model.centroid__world
    rng = np.random.default_rng(np.random.SeedSequence([int(settings.seed), 4]))
    cands, scores = [], []
    if settings.method == "random":
        a = space.random_action(rng, target)
        cands.append(a)
        scores.append(scorer(a))
    else:
        lo, hi = space.bounds()
        for f in range(model.n_fingers):
            res = cem_maximize(lambda u: scorer(space.action(f, u, target)), lo, hi, rng,
                               iterations=settings.iterations, population=settings.population,
                               elite=settings.elite or max(1, settings.population // 3))
            cands += [space.action(f, u, target) for u in res.samples]
            scores += list(res.scores)
            log.info(f"finger {f}: best {settings.score} {np.max(res.scores):.4g} of {len(res.scores)} candidates")
    cands = np.asarray(cands, float).reshape(-1, len(POKE_NAMES))
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
                score=settings.score, estimate_sha256=sha, names=list(POKE_NAMES), kind="poke",
                extra_attrs={"planner": json.dumps({**asdict(settings), "vary": list(settings.vary)}),
                             "wall_time": float(wall), "evaluations": int(scorer.evaluations),
                             "target": np.asarray(target, float)})

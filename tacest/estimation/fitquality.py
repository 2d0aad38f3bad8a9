"""Goodness of fit: is an estimate's misfit within the noise the configuration states?

A converged fit is not a right fit: a fit in a wrong basin (a short box that slid where
the real one toppled) converges too, and its objective looks fine to the solver.  Its
whitened residuals do not: where the model cannot follow the data, they exceed the noise
floor.  This module tests every fit's per-sample residuals against the configured
(``nominal``) noise floor of tacest.estimation.floor, the implementation the diagnosis
uses too: every loss term in every window of one contact state (at most WINDOW samples),
and every term's total over the fit, each a chi-square test, flagged with Bonferroni's
correction over all of them at the family-wise rate ALPHA.

A fit is *consistent* when nothing is flagged: the residuals could be the noise of the
configured levels (which are generous: the fitted residuals of a right fit sit well below
them).  The chance that a fit whose residuals are such noise is marked inconsistent is at
most ALPHA (the stated false-alarm rate).  An inconsistent fit keeps its estimate, but
its error bars are not to be trusted: the misfit says the model, the basin or the noise
levels are wrong somewhere, and the worst windows say where.

A *local misfit* (FitQuality.local_misfit) counts as consistent: flagged windows that
cover at most LOCAL_FRACTION of the samples, with no term's total flagged.  That is the
model's simplification at an instant, not a wrong basin: on fast pokes a fingertip that
slides off a tipping object's corner within a few samples turns the contact normal
faster than one frame per interval follows (the dissipation and normal terms flag the
last 3-5 samples before the release), while a fit in a wrong basin misplaces the object
over long stretches and flags term totals.  Such a fit keeps the flagged windows in
``worst``, its std is widened by ``std_scale`` all the same, and it is said in one line
(docs/estimation.md, "Goodness of fit", has the measurements behind the rule).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tacest.estimation.floor import (WINDOW, breakdown, contact_state, fit_floor, flagged_windows, residual_dof,
                                     window_tests)

#: family-wise false-alarm rate of the test: the chance that a fit whose residuals are
#: noise at the configured levels is marked inconsistent
ALPHA = 0.01
#: how many of the worst windows an estimate file keeps
N_WORST = 5
#: a misfit whose flagged windows cover at most this fraction of the samples is local
#: (FitQuality.local): one flagged window of 20 samples in a 10 s recording is 2.5 %; the
#: wrong basins seen (a box that slid where it toppled) misfit 10-60 %
LOCAL_FRACTION = 0.05


@dataclass
class FitQuality:
    """consistent : nothing flagged; alpha; n_tests : windows and totals tested; worst :
    the flagged windows, largest excess first [{run, start, stop, term, p, excess}]; terms
    : the flagged terms' totals [{run, term, contact, p, excess}]; flagged_samples : how
    many samples the flagged windows cover."""

    consistent: bool
    alpha: float
    n_tests: int
    worst: list = field(default_factory=list)
    terms: list = field(default_factory=list)
    flagged_samples: int = 0
    #: samples of all runs tested
    n_samples: int = 0
    #: the factor on the std of a fit with flagged windows: sqrt of their ‖r‖² per
    #: degree of freedom (1 where nothing is flagged)
    std_scale: float = 1.0

    @property
    def local_misfit(self) -> bool:
        """Windows are flagged, but only locally: consistent all the same (module
        docstring)."""
        return self.consistent and bool(self.worst)

    @property
    def local(self) -> bool:
        """The estimators' restart rule (they restart only from fits that are not
        local): nothing flagged, or a local misfit, which :func:`goodness_of_fit` calls
        consistent (a fast release, a stalled push: the model's simplifications at an
        instant, not a wrong basin, whose misplaced object misfits long stretches or a
        whole term)."""
        return self.consistent

    def summary(self) -> str:
        """One line: consistent, or where it is not (quality_summary)."""
        return quality_summary(self.to_json())

    def to_json(self) -> dict:
        return {"consistent": self.consistent, "local_misfit": self.local_misfit, "alpha": self.alpha,
                "n_tests": self.n_tests,
                "flagged_samples": self.flagged_samples, "n_samples": self.n_samples, "worst": self.worst,
                "terms": self.terms, "std_scale": self.std_scale}


def quality_summary(quality: dict) -> str:
    """One line of a fit-quality record (FitQuality.to_json, an estimate's fit_quality):
    consistent, or where it is not."""
    where = "; ".join(f"{w['term']} in run {w['run']} samples {w['start']}-{w['stop']} (p {w['p']:.1e})"
                      for w in quality.get("worst", [])[:3])
    if quality.get("consistent") and quality.get("local_misfit"):
        return (f"consistent with the noise floor but for a local misfit ({quality.get('flagged_samples')} of "
                f"{quality.get('n_samples')} samples): {where}: an instant the model simplifies (a fingertip that "
                f"slides off a corner at speed, a release); error bars widened x{quality.get('std_scale', 1.0):.2f}")
    if quality.get("consistent"):
        return f"consistent with the noise floor ({quality['n_tests']} tests at {quality['alpha']:g})"
    bound = quality.get("shape_at_bound") or []
    odd = quality.get("implausible") or []
    # the residual test alone passed: nothing flagged, or only a local misfit
    residuals_pass = not quality.get("terms") and (not quality.get("worst") or quality.get("local_misfit"))
    if bound and residuals_pass:
        return ("NOT a valid fit: the shape ended at a hard bound (" + ", ".join(bound) + "): the object collapsed "
                "to the smallest size allowed or grew to the largest (a wrong basin, or a size bound that does not "
                "fit the object: /prior size_bound)" + (f"; implausible friction ({', '.join(odd)})" if odd else "")
                + "; its error bars are not to be trusted")
    if odd and residuals_pass:
        return ("NOT a plausible fit: friction outside the plausible range (" + ", ".join(odd) + "), the mark of a "
                "wrong basin (a light and grippy object, a wrong shape drifting on a frictionless fingertip), or of "
                "an object outside that range ([prior] friction_plausible); its error bars are not to be trusted")
    terms = ", ".join(f"{t['term']} (p {t['p']:.1e})" for t in quality.get("terms", [])[:3])
    return ("NOT consistent with the noise floor: " + (where or "")
            + (f"; term totals {terms}" if terms else "")
            + (f"; the shape at a hard bound ({', '.join(bound)})" if bound else "")
            + (f"; implausible friction ({', '.join(odd)})" if odd else "")
            + ": the fit does not explain these data within the stated noise (a wrong basin, an unmodelled "
              "effect, or noise levels set too low); its error bars are not to be trusted")


def covered_samples(windows) -> int:
    """How many samples the windows (each with run, start, stop: [start, stop)) cover
    together: a sample flagged by two terms (the contact and the complementarity of one
    instant) counts once."""
    by_run = {}
    for w in windows:
        by_run.setdefault(int(w.run), []).append((int(w.start), int(w.stop)))
    total = 0
    for spans in by_run.values():
        end = None
        for a, b in sorted(spans):
            if end is None or a >= end:
                total += b - a
                end = b
            elif b > end:
                total += b - end
                end = b
    return total


def goodness_of_fit(residuals: list, runs: list, n_vertices: int, weights: dict = None, alpha: float = ALPHA,
                    window: int = WINDOW) -> FitQuality:
    """The test of the module docstring.  residuals : per run {term: (T,) 0.5·‖r‖² per
    sample} (RunEstimate.residuals); runs : the runs (degrees of freedom, contact
    states); n_vertices : K of the fitted shape; weights : {term: loss weight} (for the
    excess in objective units)."""
    dofs = [residual_dof(r, n_vertices) for r in runs]
    states = [contact_state(r) for r in runs]
    floor = fit_floor(residuals, dofs, states, weights=weights, window=window, mode="nominal")
    stats = window_tests(residuals, dofs, states, floor, alpha=alpha)
    totals = breakdown(stats, floor)
    n_tests = len(stats) + len(totals)
    # one family: windows and totals, Bonferroni over both (window_tests divided alpha
    # by the windows alone)
    threshold = alpha / max(n_tests, 1)
    flagged = [s for s in stats if s.p < threshold and s.excess > 0]
    for s in stats:
        s.flagged = s in flagged
    merged = flagged_windows(flagged, merge=True) if flagged else []
    worst = sorted(merged, key=lambda s: -s.excess)
    bad_terms = [r for r in totals if r["p"] < threshold and r["excess"] > 0]
    n_samples = int(sum(r.n_samples for r in runs))
    flagged_samples = covered_samples(merged)
    local = not bad_terms and flagged_samples <= LOCAL_FRACTION * n_samples
    return FitQuality(
        consistent=local, alpha=alpha, n_tests=n_tests,
        worst=[{"run": int(s.run), "start": int(s.start), "stop": int(s.stop), "term": s.term, "p": float(s.p),
                "excess": float(s.excess)} for s in worst[:N_WORST]],
        terms=[{"run": int(r["run"]), "term": r["term"], "contact": bool(r["contact"]), "p": float(r["p"]),
                "excess": float(r["excess"])} for r in sorted(bad_terms, key=lambda r: r["p"])],
        flagged_samples=flagged_samples, n_samples=n_samples,
        std_scale=float(np.sqrt(max(1.0, sum(s.S for s in flagged) / max(sum(s.n for s in flagged), 1e-12))))
        if flagged else 1.0)


"""``tacest diagnose --explore``: the diagnosis' closed loop in simulation (2-D and 3-D).

A box is recorded by tacest's simulator (2-D pymunk, or the 3-D MuJoCo world) with an
effect the diagnosis is not told about (``--inject``, or none), with ``pokes`` random
pokes by one force-sensing finger, touch alone (no pose observations) unless
``observe_pose`` (m) asks for motion capture.  Then, until the verdict names an effect
or ``budget`` actions are spent:

1. diagnose the run (the truth stripped; 2-D: tacest.diagnosis.diagnose, one run cut at
   its pokes into held-out folds; 3-D: the run cut at its pokes into sub-runs, the first
   half training, tacest.diagnosis.diagnose3d);
2. choose the next poke: ``suggest`` (tacest.diagnosis.suggest: while the verdict is
   ``none``, the poke that would best show any candidate at a typical size; when it is
   undetermined, the one that best tells the plain model and the leading candidates
   apart) or ``random`` (the planner's
   random poke of the same action space: the side-by-side baseline);
3. record it onto the run (``tacest record --plan``'s path).

The verdict is decided when it names an effect: ``none`` (no effect shown yet) and
``undetermined`` go on exploring.  DIR gets ``run.h5`` (with its truth), ``diagnosis_<n>/``
(each step's report folder), ``plan_<n>.h5``, ``summary.json`` (``steps``: actions taken,
verdict, each candidate's held-out reduction and score, wall times; the injected effect)
and ``candidates.png``: each candidate's reduction of the held-out gap against actions
taken.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from tacest.errors import TacestError

log = logging.getLogger(__name__)

POLICIES = ("suggest", "random")
#: the loop's files in its folder (its report folders are diagnosis_<n>/)
LOOP_FILES = ("run.h5", "summary.json", "candidates.png", "plan_*.h5")


@dataclass
class ExploreDiagnosisOptions:
    """effect : the hidden effect, ``NAME[:key=value,...]`` as ``tacest record --effect``
    (``none``: a clean recording); seed; object_spec; pokes : random pokes recorded
    first; budget : most actions added; policy : ``suggest`` or ``random``; poke_style :
    the action space (tacest.planning.actions); effects, max_folds, fit_iterations :
    of every diagnosis (tacest.diagnosis.diagnose.DiagnoseOptions); config_path; dim : 2
    or 3; observe_pose : m, the recordings' pose observation sigma (None: touch alone)."""

    effect: str = "none"
    seed: int = 0
    object_spec: str = "box"
    pokes: int = 4
    budget: int = 6
    policy: str = "suggest"
    poke_style: str = "dynamic"
    effects: Optional[tuple] = None
    max_folds: Optional[int] = None
    fit_iterations: Optional[int] = None
    config_path: Optional[str] = None
    dim: int = 2
    observe_pose: Optional[float] = None

    def validate(self):
        if self.policy not in POLICIES:
            raise TacestError(f"unknown policy {self.policy!r}: use {', '.join(POLICIES)}")
        if int(self.pokes) < 2:
            raise TacestError("--explore needs at least 2 random pokes to start from (a held-out fold each)")
        if int(self.budget) < 0:
            raise TacestError("--budget must be >= 0")
        if int(self.dim) not in (2, 3):
            raise TacestError(f"--dim must be 2 or 3, got {self.dim}")
        if self.observe_pose is not None and not (math.isfinite(float(self.observe_pose)) and self.observe_pose > 0):
            raise TacestError(f"--observe-pose must be > 0 m, got {self.observe_pose}")
        return self

    def diagnose_options(self):
        from tacest.diagnosis.diagnose import DiagnoseOptions

        opts = DiagnoseOptions(effects=self.effects)
        for key in ("max_folds", "fit_iterations"):
            if getattr(self, key) is not None:
                setattr(opts, key, int(getattr(self, key)))
        return opts.validate()


def decided(verdict: str) -> bool:
    """A verdict that names an effect ends the loop (module docstring)."""
    from tacest.diagnosis.diagnose import UNDETERMINED
    from tacest.model.registry import NONE

    return verdict not in (NONE, UNDETERMINED)


def explore_diagnosis(opts: ExploreDiagnosisOptions, out_dir, progress=None, executor=None) -> dict:
    """Run the loop (module docstring); returns the summary dict.  progress :
    callable(n_done, n_total) after each diagnosis; executor : where each diagnosis'
    fits run (tacest.parallel.Executor, started; None: in this process), which does not
    change the loop's results."""
    from tacest.estimation.config import load_config
    from tacest.io.outputs import replacing_files
    from tacest.sim.record import SimOptions

    opts.validate()
    if int(opts.dim) == 2:
        opts.diagnose_options()  # bad diagnosis options are an error before anything is recorded
    dim = int(opts.dim)
    out = Path(out_dir)
    from tacest.sim.effects import parse_effect

    if opts.effect != "none":
        parse_effect(opts.effect)  # a bad --inject is an error before the folder is touched
    config = load_config(opts.config_path)
    sim = SimOptions(dim=dim, object_spec=opts.object_spec, seed=int(opts.seed), pokes=int(opts.pokes),
                     effects=[] if opts.effect == "none" else [opts.effect],
                     observe_pose=opts.observe_pose).validate()
    with replacing_files(out, LOOP_FILES):  # an earlier loop's files never pass for this one's
        for old in out.glob("diagnosis_*"):
            if old.is_dir() and (old / "report.md").is_file():  # an earlier loop's report folder
                shutil.rmtree(old)
        return _loop(opts, sim, config, out, progress, executor)


def _loop(opts: ExploreDiagnosisOptions, sim, config, out: Path, progress, executor=None) -> dict:
    from tacest.diagnosis.suggest import model_of, suggest
    from tacest.io.plan import Plan, write_plan
    from tacest.planning.actions import action_space_for
    from tacest.io.run import read_run, write_run

    if int(opts.dim) == 3:
        from tacest.sim3d.record import record_sim
    else:
        from tacest.sim.record import record_sim
    run_path = out / "run.h5"
    t_all = time.perf_counter()
    write_run(record_sim(sim), run_path)
    injected = read_run(run_path).truth.effects
    steps = []
    summary = {"effect": opts.effect, "injected": injected, "options": asdict(opts), "steps": steps,
               "complete": False, "workers": _workers(executor)}
    rng = np.random.default_rng(np.random.SeedSequence([int(opts.seed), 37]))
    total = int(opts.budget) + 1
    for n in range(total):
        run = read_run(run_path)
        blind = run.replace(truth=None)
        t0 = time.perf_counter()
        diag, state_runs, candidates = _diagnose(blind, opts, config, out / f"diagnosis_{n}", executor)
        step = {"actions": n, "pokes": int(opts.pokes) + n, "samples": run.n_samples, "verdict": diag.verdict,
                "reason": diag.reason, "diagnosis_time": time.perf_counter() - t0, "candidates": candidates}
        done = decided(diag.verdict)
        if not done and n < total - 1:
            t1 = time.perf_counter()
            if opts.policy == "suggest":
                try:
                    plan = suggest(diag, state_runs, n=1, poke_style=opts.poke_style, seed=int(opts.seed) + n,
                                   config=config)[0].plan
                except TacestError as exc:  # nothing to tell apart yet: a random poke instead
                    step["suggest_error"] = str(exc)
                    plan = None
            else:
                plan = None
            if plan is None:
                model = model_of(diag, state_runs, config)
                space = action_space_for(model, opts.poke_style)
                a = space.random_action(rng, model.centroid__world)
                plan = Plan(chosen=a, candidates=a[None], scores=np.zeros(1), method="random", score="none",
                            names=list(space.poke_names))
            plan_path = out / f"plan_{n + 1}.h5"
            write_plan(plan, plan_path)
            step["next_action"] = plan.chosen_dict()
            step["plan_method"] = plan.method
            step["plan_time"] = time.perf_counter() - t1
            write_run(record_sim(sim, plan_path=plan_path, append_to=run_path), run_path)
        steps.append(step)
        log.info(f"[{n}/{total - 1} actions] verdict {diag.verdict} ({step['diagnosis_time']:.0f} s)")
        summary["wall_time"] = time.perf_counter() - t_all
        summary["verdict"] = diag.verdict
        summary["decided"] = done
        _write_summary(out, summary)  # after every step: a partial loop is readable (complete: false)
        if progress is not None:
            progress(n + 1, total)
        if done:
            break
    plot_candidates(out / "candidates.png", summary)
    summary["figure"] = "candidates.png"
    summary["complete"] = True
    _write_summary(out, summary)
    return summary


def _workers(executor) -> int | str:
    """The summary's ``workers``: 1 (this process), the local cluster's worker
    processes, or the scheduler's address (its workers are not known here)."""
    if executor is None or not executor.distributed:
        return 1
    st = executor.settings
    return st.scheduler if st.scheduler else int(st.workers)


def _write_summary(out: Path, summary: dict) -> None:
    from tacest.io.outputs import atomic_file

    with atomic_file(out / "summary.json") as tmp:
        tmp.write_text(json.dumps({"complete": False, **summary}, indent=1, default=_num) + "\n")


def _diagnose(blind, opts: ExploreDiagnosisOptions, config, folder, executor=None) -> tuple:
    """One step's diagnosis of the run ``blind`` (no truth) and its report folder:
    (diagnosis, the runs whose last state is the object's now, {candidate: reduction,
    score, status})."""
    if int(opts.dim) == 2:
        from tacest.diagnosis.diagnose import diagnose
        from tacest.diagnosis.report import write_report

        diag = diagnose([blind], "box", config=config, options=opts.diagnose_options(), executor=executor)
        write_report(diag, folder)
        return diag, [blind], {c.name: {"reduction": _num(c.reduction), "score": _num(c.score), "status": c.status}
                               for c in diag.effects}
    from tacest.diagnosis.diagnose3d import Options3D, diagnose_3d, write_report_3d
    from tacest.io.slicing import split_at_actions

    parts = [p.replace(filename=f"part{i}") for i, p in enumerate(split_at_actions(blind))]
    diag = diagnose_3d(parts, "box", config=config,
                       options=Options3D(fit_iterations=opts.fit_iterations, effects=opts.effects), executor=executor)
    write_report_3d(diag, folder)
    return diag, diag.base_runs, {e["name"]: {"reduction": _num(e["reduction"]), "score": _num(e.get("score")),
                                              "status": diag.fits[e["name"]].status} for e in diag.effects}


def _num(v):
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return f if np.isfinite(f) else None


def plot_candidates(path, summary: dict) -> None:
    """Each candidate's held-out reduction against actions taken (one line per
    candidate; the verdict of each step above the axis)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = summary["steps"]
    names = sorted({c for s in steps for c in s["candidates"]})
    fig, ax = plt.subplots(figsize=(7, 3.6))
    for name in names:
        xs = [s["actions"] for s in steps if name in s["candidates"]]
        ys = [s["candidates"][name]["reduction"] for s in steps if name in s["candidates"]]
        ys = [np.nan if y is None else y for y in ys]
        ax.plot(xs, ys, marker="o", lw=1, label=name)
    ax.axhline(0.0, color="k", lw=0.6)
    for s in steps:
        ax.annotate(s["verdict"], (s["actions"], 1.02), xycoords=("data", "axes fraction"), fontsize=6,
                    ha="center", rotation=30)
    ax.set_xlabel("actions taken (after the random pokes)")
    ax.set_ylabel("held-out gap closed")
    ax.set_title(f"hidden effect: {summary['effect']}, policy {summary['options']['policy']}", fontsize=9, pad=22)
    ax.legend(fontsize=6, ncol=3)
    fig.subplots_adjust(left=0.11, right=0.97, bottom=0.14, top=0.8)
    fig.savefig(path, dpi=90)
    plt.close(fig)

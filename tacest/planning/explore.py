"""``tacest explore``: the closed loop in the simulated world — poke, estimate, plan, repeat.

``dim`` 2 runs it in the pymunk world, ``dim`` 3 in the MuJoCo world (tacest.sim3d:
1–3 fingers, contact and normal only unless ``force_stream``; boxes estimated as
``box``, random polytopes as ``polytope:12``; planned over approach azimuth and
elevation, tacest.planning.actions.ActionSpace3).  The loop is the same in both:

Step 1 records the first poke of a new simulated object (tacest.sim.record.record_sim
with one poke: the simulator's random poke of the seed, aimed at the object's centroid
where it was placed; no estimate exists yet, so it is the same for every policy).  Then,
for n = 1 .. N:

1. estimate the run so far (tacest.estimation.estimator.estimate_runs) -> ``estimate_<n>.h5``;
   the last step's estimate is one more start, its trajectory continued over the newest
   poke (estimator.previous_start_2d, estimator3d.previous_start), compared by
   objective with the others;
   score it against the truth (tacest.evaluation.metrics.evaluate);
2. if n < N: plan the next poke with the policy (tacest.planning.planner.plan_next,
   aimed at the estimated centroid) -> ``plan_<n>.h5``, execute it in the simulator
   (record_sim(plan_path=..., append_to=run.h5): the world continues from its last true
   state) -> ``run.h5``.

A failed estimate is a recorded failure (its step has ``estimate_status`` "failed",
the solver's message and no metrics).  The next poke is then planned, with the same
policy, from the estimator's own starting point instead (:func:`start_guess_estimate`:
the shape and push-tracked trajectory the estimator would start from, the prior's mass
and frictions, no observed information), and the step says so (``planned_from``
``"start guess"``); the truth is never used to choose a poke.  At the end:
``summary.json`` and ``learning_curve.png``; in 3-D also ``view_3d.png`` (the true and
estimated shapes at the end, the finger paths and the touched points) and
``view_3d.html`` (the same, animated, for a browser: tacest.view.html3d).
"""

from __future__ import annotations

import logging

import json
import math
import os
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from tacest.errors import SolveFailedError, TacestError

log = logging.getLogger(__name__)

POLICIES = ("eig", "random", "identity")
#: metrics copied from tacest eval into every step of the summary
STEP_METRICS = ("chamfer", "chamfer_body", "pose_position_rmse", "pose_angle_rmse", "mass_rel", "inertia_rel",
                "friction_ground_rel", "friction_finger_rel")


@dataclass
class ExploreOptions:
    """Settings of one closed loop.

    object_spec : ``box``, ``box:W,H``, ``polygon``, ``polygon:K`` or a vertex file
    (3-D: ``box``, ``box:W,H,D``, ``polytope``, ``polytope:K`` or a vertex file);
    dim : 2 or 3; fingers : fingertips (1–3); force_stream : record a force stream
    (None: yes in 2-D, no in 3-D: contact and normal only); information : the planner's
    information construction (tacest.planning.planner.PlanSettings; None: its default);
    seed : the simulator's seed (object, first poke, noise); policy : eig | random |
    identity; pokes : N >= 1; shape : estimator shape (default ``box`` for boxes,
    ``polygon:8`` otherwise, ``polytope:12`` in 3-D); score : logdet | A | D | E;
    config_path : estimator TOML;
    vary : planner variables besides the angle; poke_style : gentle | dynamic, the first
    poke's style (tacest record --poke-style) and the planner's action space (dynamic:
    fast pokes whose speed and aim height are chosen, tacest.planning.actions); noise_* :
    sensor noise of the simulator
    (tacest record's defaults); iterations, population : CEM settings;
    fingers_per_action : fingers moving together in each planned action (3-D only).
    """

    object_spec: str = "box"
    seed: int = 0
    policy: str = "eig"
    pokes: int = 8
    shape: str | None = None
    score: str = "logdet"
    config_path: str | None = None
    vary: tuple = field(default_factory=tuple)
    noise_force: float = 0.02
    noise_position: float = 1e-4
    noise_normal: float = 0.02
    iterations: int = 4
    population: int = 12
    dim: int = 2
    fingers: int = 1
    force_stream: bool | None = None
    information: str | None = None
    poke_style: str = "gentle"
    fingers_per_action: int = 1

    def validate(self) -> "ExploreOptions":
        if int(self.dim) not in (2, 3):
            raise TacestError(f"--dim must be 2 or 3, got {self.dim}")
        if not 1 <= int(self.fingers) <= 3:
            raise TacestError(f"--fingers must be 1, 2 or 3, got {self.fingers}")
        if self.policy not in POLICIES:
            raise TacestError(f"unknown policy {self.policy!r}: use {', '.join(POLICIES)}")
        if int(self.pokes) < 1:
            raise TacestError(f"--pokes must be >= 1, got {self.pokes}")
        if int(self.seed) < 0:
            raise TacestError(f"--seed must be >= 0, got {self.seed}")
        from tacest.sim.pokes import check_fingers_per_action

        check_fingers_per_action(self.fingers_per_action, self.fingers, self.dim)
        return self

    @property
    def estimator_shape(self) -> str:
        if self.shape:
            return self.shape
        if str(self.object_spec).strip().startswith("box"):
            return "box"
        return "polytope:12" if int(self.dim) == 3 else "polygon:8"

    @property
    def records_force(self) -> bool:
        return (int(self.dim) == 2) if self.force_stream is None else bool(self.force_stream)

    def plan_settings(self, n: int):
        """The planner's settings for the poke after step ``n``."""
        from tacest.planning.planner import PlanSettings

        return PlanSettings(method=self.policy, score=self.score, seed=plan_seed(self.seed, n), vary=tuple(self.vary),
                            iterations=self.iterations, population=self.population,
                            information=self.information, poke_style=self.poke_style,
                            fingers_per_action=int(self.fingers_per_action)).validate()


def _write_json(path: Path, obj) -> None:
    tmp = path.with_name(f".{path.name}.part")
    tmp.write_text(json.dumps(obj, indent=2, allow_nan=False) + "\n")
    os.replace(tmp, path)


def explore(opts: ExploreOptions, out_dir, progress=None) -> dict:
    """Run the closed loop (module docstring); returns the summary dict.

    Progress lines go to the module's logger; progress : callable(n_done, n_total) after
    each poke (the CLI's progress bar).  Raises TacestError for bad options or an
    output folder that is a file.
    """
    from tacest.estimation.config import load_config
    from tacest.evaluation.metrics import evaluate, to_jsonable
    from tacest.io.estimate import read_estimate, write_estimate
    from tacest.io.plan import write_plan
    from tacest.io.run import read_run, write_run
    from tacest.planning.actions import describe_action
    from tacest.planning.planner import plan_next
    from tacest.sim.record import SimOptions

    opts.validate()
    record_sim, estimate = _world_of(int(opts.dim))
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise TacestError(f"{out}: exists and is not a folder")
    _check_object(opts.object_spec, int(opts.dim))  # a bad --object is an error before any file is touched
    opts.plan_settings(1)  # so are planner settings that do not go together
    out.mkdir(parents=True, exist_ok=True)
    config = load_config(opts.config_path)
    shape = opts.estimator_shape
    sim = SimOptions(dim=int(opts.dim), object_spec=opts.object_spec, seed=int(opts.seed), pokes=1,
                     fingers=int(opts.fingers), force_stream=opts.records_force, noise_force=opts.noise_force,
                     poke_style=opts.poke_style,
                     noise_position=opts.noise_position, noise_normal=opts.noise_normal).validate()
    run_path = out / "run.h5"
    for stale in [run_path, out / "summary.json", out / "learning_curve.png", out / "view_3d.png",
                  out / "view_3d.html", *out.glob("estimate_*.h5"), *out.glob("plan_*.h5")]:
        stale.unlink(missing_ok=True)  # never mistake an earlier loop's files for this one's
    t_all = time.perf_counter()
    N = int(opts.pokes)
    steps = []
    summary = {"object": opts.object_spec, "dim": int(opts.dim), "fingers": int(opts.fingers),
               "force": opts.records_force, "seed": int(opts.seed), "policy": opts.policy, "pokes": N,
               "shape": shape, "score": opts.score, "fingers_per_action": int(opts.fingers_per_action),
               "information": opts.plan_settings(1).information_for(int(opts.dim)),
               "options": {**asdict(opts), "vary": list(opts.vary)},
               "steps": steps}

    t0 = time.perf_counter()
    write_run(record_sim(sim), run_path)
    t_record = time.perf_counter() - t0
    previous = None  # the last estimate: one more start for the next one
    for n in range(1, N + 1):
        run = read_run(run_path)
        step = {"pokes": n, "samples": run.n_samples, "data_time": float(run.time[-1] - run.time[0]),
                "record_time": t_record}
        # -- estimate ----------------------------------------------------------------
        t0 = time.perf_counter()
        est = None
        try:
            est_obj = estimate([run], shape, config=config, previous=previous)
            est_path = out / f"estimate_{n}.h5"
            write_estimate(est_obj, est_path)
            est = previous = read_estimate(est_path)
            step["estimate_status"] = est.solver_status
        except SolveFailedError as exc:
            step["estimate_status"] = "failed"
            step["estimate_error"] = str(exc)
        step["estimate_time"] = time.perf_counter() - t0
        if est is not None:
            report = evaluate(est, run, run_index=0)
            step.update({k: report[k] for k in STEP_METRICS})
            step["params"] = report["params"]
            step["fit_consistent"] = est.consistent
        else:
            step.update({k: None for k in STEP_METRICS})
        msg = f"[{n}/{N}] {run.n_samples} samples; estimate {step['estimate_status']} ({step['estimate_time']:.1f} s)"
        if est is not None:
            msg += f": chamfer {1e3 * step['chamfer']:.2f} mm, mass error {_pct(step['mass_rel'])}, " \
                   f"ground friction error {_pct(step['friction_ground_rel'])}" \
                   + ("" if est.consistent is not False else " (fit NOT consistent with its data)")
        # -- plan and execute the next poke ------------------------------------------
        if n < N:
            plan_path = out / f"plan_{n}.h5"
            source = est
            step["planned_from"] = "estimate"
            if est is None:
                source = start_guess_estimate([run], shape, config)
                step["planned_from"] = "start guess"
            plan = plan_next(source, [run], opts.plan_settings(n))
            write_plan(plan, plan_path)
            step["plan_time"] = float(plan.extra_attrs["wall_time"])
            step["plan_score"] = float(plan.scores[np.argmax(np.all(plan.candidates == plan.chosen, 1))])
            step["next_action"] = plan.chosen_dict()
            msg += f"; plan {opts.policy} from the {step['planned_from']} ({step['plan_time']:.1f} s): " \
                   + describe_action(plan.chosen_dict())
            t1 = time.perf_counter()
            write_run(record_sim(sim, plan_path=plan_path, append_to=run_path), run_path)
            t_record = time.perf_counter() - t1
        steps.append(to_jsonable(step))
        log.info(msg)
        if progress is not None:
            progress(n, N)
        summary["wall_time"] = time.perf_counter() - t_all
        _write_json(out / "summary.json", to_jsonable(summary))  # after every step: a partial loop is readable
    summary["wall_time"] = time.perf_counter() - t_all
    summary["learning_curve"] = "learning_curve.png"
    plot_learning_curve(out / "learning_curve.png", [summary])
    if int(opts.dim) == 3:
        summary.update(_views_3d(out, run_path, N, f"{opts.object_spec}, seed {opts.seed}, policy {opts.policy}"))
    _write_json(out / "summary.json", to_jsonable(summary))
    return summary


def _world_of(dim: int):
    """(record_sim, estimate) of the simulated world and the estimator of ``dim``."""
    if dim == 3:
        from tacest.estimation.estimator3d import estimate_3d as estimate
        from tacest.sim3d.record import record_sim
    else:
        from tacest.estimation.estimator import estimate_2d as estimate
        from tacest.sim.record import record_sim
    return record_sim, estimate


def _check_object(object_spec: str, dim: int) -> None:
    """TacestError (one line) for an --object the simulator of ``dim`` cannot build."""
    if dim == 3:
        from tacest.sim3d.objects import make_shape as sim_object
    else:
        from tacest.sim.objects import make_shape as sim_object
    sim_object(object_spec, np.random.default_rng(0))


def _views_3d(out: Path, run_path: Path, N: int, what: str) -> dict:
    """view_3d.png and view_3d.html of the last estimate that exists (else the run
    alone), titled ``what`` and the estimate's name; the summary's entries naming them.
    A failed view is logged, not fatal: the loop's results are already on disk."""
    from tacest.view.html3d import write_html_3d
    from tacest.view.png3d import write_png_3d
    from tacest.view.scene import load_scene

    last = next((out / f"estimate_{n}.h5" for n in range(N, 0, -1) if (out / f"estimate_{n}.h5").exists()), None)
    scene = load_scene(last, run_path) if last is not None else load_scene(run_path)
    scene.title = f"{what}: truth (green), {last.name if last else 'no estimate'} (blue), fingers, touched points (red)"
    views = {}
    for name, write in (("view_3d.png", write_png_3d), ("view_3d.html", write_html_3d)):
        try:
            write(scene, out / name)
            views[name.replace(".", "_")] = name
        except (TacestError, OSError, ValueError) as exc:
            log.warning(f"{out / name}: not written ({exc})")
    return views


def _step_values(group: list, key: str, scale: float) -> np.ndarray:
    """(n_summaries, n_max) ``scale`` × each step's ``key`` by poke count; NaN where missing."""
    n_max = max(len(s["steps"]) for s in group)
    vals = np.full((len(group), n_max), np.nan)
    for i, s in enumerate(group):
        for st in s["steps"]:
            v = st.get(key)
            if v is not None and 1 <= st["pokes"] <= n_max:
                vals[i, st["pokes"] - 1] = scale * v
    return vals


def _median_columns(vals: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(vals, 0)


def start_guess_estimate(runs, shape: str, config):
    """An Estimate (not a result: ``success`` False, status ``"start guess"``, no
    information) holding the estimator's starting point for ``runs``: the start shape
    (tacest.estimation.initial.choose_start_shape), its push-tracked trajectories, the
    prior's mass, uniform-density inertia and frictions.  What a planner can still aim
    with when the estimate failed.  3-D runs: :func:`start_guess_estimate_3d`."""
    if runs and int(runs[0].dim) == 3:
        return start_guess_estimate_3d(runs, shape, config)
    from tacest.estimation.data import choose_scales
    from tacest.estimation.initial import choose_start_shape, initial_extents, start_trajectories
    from tacest.geometry.polygon import polygon_inertia, signed_area
    from tacest.geometry.shapes import make_shape, numeric_vertices
    from tacest.io.estimate import Estimate, RunEstimate
    from tacest.model.stage2d import StageModel2D

    sh = make_shape(shape)
    scales = choose_scales(runs, config)
    w, h = initial_extents(runs, scales.L)
    problem = StageModel2D(sh)
    s0 = choose_start_shape(problem, runs, scales, sh.initial(w / scales.L, h / scales.L))
    trajs = start_trajectories(problem, runs, scales, s0)
    V = numeric_vertices(sh, s0, scales.L)
    m = float(scales.m0)
    inertia = polygon_inertia(V if signed_area(V) > 0 else V[::-1], m)
    mu = float(config.prior.friction)
    return Estimate(dim=2, shape=sh.name, vertices=V,
                    params={"mass": m, "inertia": inertia, "friction_ground": mu, "friction_finger": mu},
                    runs=[RunEstimate(pose=np.asarray(t, float), velocity=np.zeros_like(t)) for t in trajs],
                    solver_status="start guess", success=False, information=None, config=config.to_dict())


def start_guess_estimate_3d(runs, shape: str, config):
    """The 3-D :func:`start_guess_estimate`: tacest.estimation.estimator3d.Estimator3D's
    initial guess (start shape, uniform-density inertia, the prior's mass and frictions,
    the start poses) as an Estimate with status ``"start guess"`` and no information."""
    from tacest.estimation.estimator3d import Estimator3D
    from tacest.io.estimate import Estimate, RunEstimate

    e = Estimator3D(runs, shape, config)
    z0 = e.initial_guess()
    V, mass, inertia, mu_g, mu_f = e.physical(z0)
    _, X, _, _ = e.problem.split(z0)  # (7, samples of every run) scaled poses
    run_ests = []
    for i, run in enumerate(runs):
        Xi = np.asarray(X, float)[:, e.layout.run_samples(i)]
        run_ests.append(RunEstimate(pose=np.concatenate([Xi[:3].T * e.scales.L, Xi[3:].T], 1),
                                    velocity=np.zeros((run.n_samples, 6))))
    return Estimate(dim=3, shape=e.shape.name, vertices=V,
                    params={"mass": mass, "inertia": inertia, "friction_ground": mu_g, "friction_finger": mu_f},
                    runs=run_ests, solver_status="start guess", success=False, information=None,
                    config=config.to_dict(), extra_attrs={"length_scale": e.scales.L, "mass_scale": e.scales.m0})


def plan_seed(seed: int, n: int) -> int:
    """A planner seed per (loop seed, step), independent of the simulator's streams."""
    return int(np.random.SeedSequence([int(seed), 7, int(n)]).generate_state(1)[0])


def _pct(v):
    return "n/a" if v is None or not math.isfinite(v) else f"{100 * v:.1f} %"


def plot_learning_curve(path, summaries: list, labels=None) -> None:
    """Chamfer (mm) and relative parameter errors (%) against the number of pokes, and
    (a second row, where every step has ``data_time``) against the seconds of recorded
    data.

    summaries : explore summaries (one line each; with several per label, e.g. from a
    benchmark, the median over them with the 25–75 % band, over the estimates that
    succeeded: a failed one leaves a gap; on the seconds row, each poke count is drawn
    at the median seconds of data it took); labels : one per summary
    (default: its policy).
    """
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    from tacest.evaluation.plots import plain_log_axis, readable_linear_axis

    labels = labels or [s["policy"] for s in summaries]
    groups = {}
    for s, lab in zip(summaries, labels):
        groups.setdefault(lab, []).append(s)
    keys = [("chamfer", "Chamfer (mm)", 1e3), ("mass_rel", "mass error (%)", 100.0),
            ("friction_ground_rel", "ground friction error (%)", 100.0),
            ("friction_finger_rel", "finger friction error (%)", 100.0)]
    by_time = all(st.get("data_time") is not None for s in summaries for st in s["steps"])
    rows = ["pokes", "data_time"] if by_time else ["pokes"]
    fig, axes = plt.subplots(len(rows), len(keys), figsize=(4.2 * len(keys), 3.6 * len(rows)), squeeze=False)
    for row, x_key in zip(axes, rows):
        for ax, (key, title, scale) in zip(row, keys):
            drawn = []
            for lab, group in groups.items():
                vals = _step_values(group, key, scale)
                x = np.arange(1, vals.shape[1] + 1, dtype=float)
                if x_key == "data_time":
                    x = _median_columns(_step_values(group, "data_time", 1.0))
                with warnings.catch_warnings():  # an all-NaN column (every estimate failed) stays NaN
                    warnings.simplefilter("ignore", RuntimeWarning)
                    med = np.nanmedian(vals, 0)
                    lo, hi = np.nanpercentile(vals, 25, 0), np.nanpercentile(vals, 75, 0)
                line, = ax.plot(x, med, marker="o", ms=3,
                                label=f"{lab} (n={len(group)})" if len(group) > 1 else lab)
                drawn += [med, lo, hi] if len(group) > 1 else [med]
                if len(group) > 1:
                    ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.15, lw=0)
            if x_key == "pokes":
                ax.set_xlabel("pokes")
                ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # a poke count is a whole number
            else:
                ax.set_xlabel("recorded data (s)")
            ax.set_title(title, fontsize=10)
            ax.grid(alpha=0.3)
            if key == "chamfer":
                ax.set_yscale("log")
                plain_log_axis(ax)
            else:
                readable_linear_axis(ax, np.concatenate(drawn) if drawn else [])
    axes = axes[0]
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    tmp = path.with_name(f".{path.name}.part")
    try:
        fig.savefig(tmp, dpi=110, format=path.suffix.lstrip(".").lower() or "png")
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        tmp.unlink(missing_ok=True)

"""``tacest demo``: the main job on a built-in simulated example, through the library.

record (a 2-D box, 6 random pokes, with truth) -> estimate (shape ``box``) -> eval
(JSON and a figure) -> a short summary.  Stages this version does not have yet (plan,
diagnose) are named as such.  A failed solve is reported as a failure (exit status 2),
never as an estimate.
"""

from __future__ import annotations

import importlib.util
import json
import math
import time

import click

from tacest.cli.logs import warn_fit_quality

#: the built-in example
DEMO_OBJECT = "box"
DEMO_POKES = 6
DEMO_SHAPE = "box"
#: the demo's files in its output folder
DEMO_FILES = ("run.h5", "estimate.h5", "eval.json", "eval.png")
#: later stages, by CLI module; each is run only if its module exists
LATER_STAGES = (("plan", "tacest.cli.plan"), ("diagnose", "tacest.cli.diagnose"))


def _available(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


@click.command()
@click.option("-o", "--output", "out_dir", type=click.Path(file_okay=False), default="demo_out", show_default=True,
              help="Folder for run.h5, estimate.h5, eval.json and eval.png (created if missing).")
@click.option("--seed", type=click.IntRange(min=0), default=1, show_default=True,
              help="Random seed of the simulated object, pokes and noise.")
@click.option("--quiet", is_flag=True, help="No progress output (the summary is still printed).")
def demo(out_dir, seed, quiet):
    """Record a simulated 2-D box with 6 pokes, estimate it, score the estimate
    against the truth, and print a summary.  Files go to OUTPUT."""
    from tacest.cli.logs import setup_logging
    from tacest.io.outputs import replacing_files

    log = setup_logging(quiet)

    def progress(msg):
        log.info(msg)

    # outputs of an earlier demo are removed, never mistaken for this one's (put back on Ctrl-C)
    with replacing_files(out_dir, DEMO_FILES) as out:
        run_path, est_path = out / "run.h5", out / "estimate.h5"
        json_path, png_path = out / "eval.json", out / "eval.png"
        lines = _demo(run_path, est_path, json_path, png_path, seed, progress)
    click.echo("\n".join(lines))


def _demo(run_path, est_path, json_path, png_path, seed, progress) -> list:
    """record -> estimate -> eval into the given files; returns the summary lines."""
    from tacest.dims import estimate_runs
    from tacest.errors import SolveFailedError
    from tacest.estimation.config import load_config
    from tacest.evaluation.metrics import evaluate, to_jsonable
    from tacest.evaluation.plots import plot_evaluation
    from tacest.io.estimate import read_estimate, write_estimate
    from tacest.io.run import read_run, write_run
    from tacest.sim.record import SimOptions, record_sim

    t_all = time.perf_counter()

    # -- record ----------------------------------------------------------------------
    t0 = time.perf_counter()
    opts = SimOptions(dim=2, object_spec=DEMO_OBJECT, seed=seed, pokes=DEMO_POKES)
    write_run(record_sim(opts), run_path)
    run = read_run(run_path)  # as every stage sees it (validated, with its file name)
    t_record = time.perf_counter() - t0
    progress(f"record: wrote {run_path} ({run.n_samples} samples, {t_record:.1f} s)")

    # -- estimate --------------------------------------------------------------------
    t0 = time.perf_counter()
    try:
        est = estimate_runs([run], DEMO_SHAPE, config=load_config(None), method="implicit")
    except SolveFailedError as exc:
        raise SolveFailedError(f"demo: solve failed on {run_path}: {exc}") from None
    write_estimate(est, est_path)
    warn_fit_quality(est)
    t_estimate = time.perf_counter() - t0
    est = read_estimate(est_path)
    progress(f"estimate: wrote {est_path} ({est.solver_status}, {est.iterations} iterations, {t_estimate:.1f} s)")

    # -- eval ------------------------------------------------------------------------
    t0 = time.perf_counter()
    report, series = evaluate(est, run, run_index=0, return_series=True)
    plot_evaluation(png_path, report, series, est, run, run_index=0)
    report["plot"] = str(png_path)
    json_path.write_text(json.dumps(to_jsonable(report), allow_nan=False, indent=2) + "\n")
    t_eval = time.perf_counter() - t0

    # -- summary ---------------------------------------------------------------------
    t_total = time.perf_counter() - t_all
    p = report["params"]
    lines = [
        f"tacest demo (seed {seed}): simulated 2-D {DEMO_OBJECT}, {DEMO_POKES} pokes, {run.n_samples} samples",
        f"record    {run_path}  ({t_record:.1f} s)",
        f"estimate  {est_path}  shape {DEMO_SHAPE}: {est.solver_status}, {est.iterations} iterations "
        f"({t_estimate:.1f} s)",
        f"eval      {json_path}, {png_path}  ({t_eval:.1f} s)",
        f"  Chamfer, placed shapes (mean over time)  {_mm(report['chamfer'])}",
        f"  Chamfer, shape alone (aligned)           {_mm(report['chamfer_body'])}",
        f"  pose RMSE                                {_mm(report['pose_position_rmse'])}, "
        f"{_deg(report['pose_angle_rmse'])}",
        f"  mass             {_param(p['mass'], 'kg')}",
        f"  friction ground  {_param(p['friction_ground'], '')}",
        f"  friction finger  {_param(p['friction_finger'], '')}",
    ]
    for name, module in LATER_STAGES:
        if _available(module):
            lines.append(f"{name}: available as 'tacest {name}' (not run by this demo)")
        else:
            lines.append(f"{name}: not available in this version yet")
    lines.append(f"wall time {t_total:.1f} s")
    return lines


def _finite(v):
    try:
        return v is not None and math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


def _mm(v):
    return f"{1e3 * float(v):.2f} mm" if _finite(v) else "n/a"


def _deg(v):
    return f"{math.degrees(float(v)):.2f} deg" if _finite(v) else "n/a"


def _num(v, unit):
    return (f"{float(v):#.3g} {unit}".strip()) if _finite(v) else "n/a"


def _param(entry, unit):
    """'0.412 kg (truth 0.398 kg, error 3.5 %)', flagged when the data cannot tell it."""
    text = f"{_num(entry['estimate'], unit)} (truth {_num(entry['truth'], unit)}"
    text += f", error {100 * entry['rel']:.1f} %)" if _finite(entry.get("rel")) else ")"
    if entry.get("identifiable") is False:
        text += "  poorly determined by these data (one sigma above half the value)"
    return text

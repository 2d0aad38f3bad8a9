"""``tacest diagnose``: where and why the model disagrees with recordings."""

from __future__ import annotations

import functools
import json
import logging

import click

from tacest.cli.parallel import executor, parallel_options
from tacest.parallel import machine_workers


@click.command()
@click.argument("runs", nargs=-1, required=False, type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(file_okay=False), required=True,
              help="Report folder to write (report.md, PNG figures, diagnosis.json).")
@click.option("--estimate", "estimate_path", type=click.Path(dir_okay=False), default=None,
              help="An estimate of exactly these runs with the plain model (saves the first fit).")
@click.option("--shape", default=None, help="Shape parameterization: box or polygon:K "
              "(default: the estimate's, else box).")
@click.option("--effects", default=None, metavar="a,b,...",
              help="Candidate effects to compare (default: every SPEC effect; 3-D: every one the 3-D model has).")
@click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="Estimator settings (TOML; `tacest config --defaults` prints every key).")
@click.option("--window", type=click.IntRange(min=1), default=None,
              help="Longest residual window, samples (default 20).")
@click.option("--alpha", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=None,
              help="False-alarm rate of the window tests (default 0.01).")
@click.option("--max-folds", type=click.IntRange(min=2), default=None,
              help="Folds of the held-out comparison (default 3).")
@click.option("--fit-iterations", type=click.IntRange(min=10), default=None,
              help="IPOPT iterations per stage of every candidate and held-out fit (default 150).")
@click.option("--max-candidates", type=click.IntRange(min=1), default=None,
              help="Refit only this many candidates, ranked by their residual signature (default: all).")
@click.option("--floor", "floor_mode", type=click.Choice(["calibrated", "nominal"]), default="calibrated",
              show_default=True, help="Noise floor: levels from the data (capped at the configured noise) "
              "or the configured noise levels themselves.")
@click.option("--reach", type=click.FloatRange(min=0), default=None, metavar="M",
              help="No action at a distance in every fit: a ground impulse at a vertex more than M m up "
              "costs its height (noise.complementarity_reach; default 0.01; 0: off). 2-D runs.")
@click.option("--cold-starts", type=click.Choice(["all", "transforms", "none"]), default=None,
              help="Which candidates' fits to all data also start from the estimator's own starts, beside the "
              "plain fit's: every candidate's, the data transforms' (latency, time_scale), or none (default: "
              "the diagnosis' default, docs/diagnosis.md). 2-D runs.")
@click.option("--screen-by-fit", is_flag=True, help="Do not hold out a candidate whose fit to all data improves on "
              "the plain model's by less than its penalty: faster, but an effect seen only across runs or pokes "
              "can be missed (docs/diagnosis.md). 2-D runs.")
@click.option("--suggest", type=click.IntRange(min=1), default=None, metavar="N",
              help="Also write N plan files (suggest_<k>.h5) of the pokes that best tell the leading candidates "
              "apart, or, while no effect shows (verdict none), that would best show any candidate at a typical "
              "size (docs/diagnosis.md).")
@click.option("--poke-style", type=click.Choice(["gentle", "dynamic"]), default="dynamic", show_default=True,
              help="Action space of --suggest: the planner's gentle or dynamic pokes.")
@click.option("--explore", is_flag=True, help="No RUNS: the closed loop in simulation: record a box with "
              "--inject hidden, diagnose, add the suggested (or --policy random) poke, until the verdict names "
              "an effect or --budget actions are spent (docs/diagnosis.md).")
@click.option("--inject", default="none", show_default=True, metavar="NAME[:key=value,...]",
              help="--explore: the effect the simulator adds (as tacest record --effect), hidden from the diagnosis.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="--explore: the recording's seed.")
@click.option("--pokes", type=click.IntRange(min=2), default=4, show_default=True,
              help="--explore: random pokes recorded before the first diagnosis.")
@click.option("--budget", type=click.IntRange(min=0), default=6, show_default=True,
              help="--explore: most actions added.")
@click.option("--policy", type=click.Choice(["suggest", "random"]), default="suggest", show_default=True,
              help="--explore: how the added pokes are chosen.")
@click.option("--dim", type=click.Choice(["2", "3"]), default="2", show_default=True,
              help="--explore: the simulated world (2: pymunk; 3: MuJoCo), one force-sensing finger.")
@click.option("--observe-pose", type=click.FloatRange(min=0, min_open=True), default=None, metavar="SIGMA",
              help="--explore: the recordings observe the object's pose with this position sigma (m, as motion "
                   "capture); default: touch alone.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@click.option("--quiet", is_flag=True, help="No progress output.")
@parallel_options
def diagnose(runs, output, estimate_path, shape, effects, config_path, window, alpha, max_folds, fit_iterations,
             max_candidates, floor_mode, reach, cold_starts, screen_by_fit, suggest, poke_style, explore, inject, seed,
             pokes, budget, policy, dim, observe_pose, as_json, quiet, workers, scheduler):
    """Diagnose where and why the model disagrees with RUNS (run files of one object):
    residuals against the noise floor, candidate effects compared on held-out data,
    the verdict (an effect or none).  The fits run in this process unless --workers or
    --scheduler sends them to a Dask cluster (same results).  See docs/diagnosis.md
    and docs/parallel.md."""
    from tacest.diagnosis.candidates import parse_effect_list
    from tacest.diagnosis.diagnose import DiagnoseOptions, check_heldout_data
    from tacest.diagnosis.diagnose import diagnose as run_diagnosis
    from tacest.diagnosis.report import write_report
    from tacest.errors import TacestError
    from tacest.estimation.config import load_config
    from tacest.io.estimate import read_estimate
    from tacest.io.outputs import check_output
    from tacest.io.run import read_runs
    from tacest.linear_solver import check_linear_solver

    from tacest.cli.logs import setup_logging

    setup_logging(quiet)
    _check_modes(explore)
    ex = executor(workers, scheduler)  # the options checked before any work
    if explore:
        return _explore(runs, output, inject, seed, pokes, budget, policy, poke_style, effects, max_folds,
                        fit_iterations, config_path, as_json, quiet, int(dim), observe_pose, ex)
    if not runs:
        raise TacestError("diagnose needs RUNS (or --explore to record them in simulation)")
    out = check_output(output, inputs=[*runs, estimate_path, config_path], folder=True)
    config = load_config(config_path)
    check_linear_solver(config.solver.linear_solver)
    loaded = read_runs(runs)
    if suggest and not loaded[-1].n_fingers:  # before hours of fits, not after
        raise TacestError("--suggest: the runs have no fingertip to poke with")
    if any(r.dim == 3 for r in loaded):  # 3-D runs: tacest/diagnosis/diagnose3d.py
        from tacest.diagnosis.diagnose3d import Options3D, diagnose_3d, write_report_3d

        if estimate_path or reach is not None or cold_starts is not None or screen_by_fit:
            raise TacestError("--estimate, --reach, --cold-starts and --screen-by-fit are for 2-D runs")
        names3 = tuple(n.strip() for n in effects.split(",") if n.strip()) if effects else None
        opts3 = Options3D(fit_iterations=fit_iterations, effects=names3, floor=floor_mode or "calibrated")
        for key, val in (("window", window), ("alpha", alpha)):
            if val is not None:
                setattr(opts3, key, val)
        with ex:
            diag = diagnose_3d(loaded, shape or "box", config=config, options=opts3, executor=ex)
        extra = _suggestions(diag, diag.base_runs, suggest, poke_style, config) if suggest else None
        _report(diag, write_report_3d, out, as_json, quiet, extra)
        _hint_workers(ex)
        return
    names = parse_effect_list(effects)
    est = read_estimate(estimate_path) if estimate_path else None
    shape = shape or (est.shape if est is not None else "box")
    opts = DiagnoseOptions(effects=names, floor=floor_mode, fit_screen=screen_by_fit)
    for key, val in (("window", window), ("alpha", alpha), ("max_folds", max_folds),
                     ("fit_iterations", fit_iterations), ("max_candidates", max_candidates), ("reach", reach),
                     ("cold_starts", cold_starts)):
        if val is not None:
            setattr(opts, key, val)
    check_heldout_data(loaded)  # before any fit: without held-out data nothing can be decided
    with ex:
        diag = run_diagnosis(loaded, shape, config=config, options=opts, estimate=est, executor=ex)
    extra = _suggestions(diag, loaded, suggest, poke_style, config) if suggest else None
    _report(diag, write_report, out, as_json, quiet, extra)
    _hint_workers(ex)


def _suggestions(diag, runs, n, poke_style, config):
    """``extra(obj)`` of :func:`_report` writing the ``n`` suggested plans
    (tacest.diagnosis.suggest).  When no poke can be suggested the finished diagnosis is
    still written, with a note, and the command ends with the reason (exit 2) after it."""
    from tacest.diagnosis.suggest import suggest, suggestion_writer
    from tacest.errors import TacestError

    try:
        found = suggest(diag, runs, n=n, poke_style=poke_style, config=config)
    except TacestError as exc:
        err = str(exc)

        def note(obj):
            obj["suggestions_error"] = err
            return lambda tmp: _append_note(tmp, f"No suggested experiment: {err}")

        note.error = err
        return note
    return functools.partial(suggestion_writer, found)


def _append_note(tmp, text) -> list:
    with open(tmp / "report.md", "a") as fh:
        fh.write(f"\n{text}\n")
    return []


#: options of --explore only, and options of a diagnosis of given runs only
EXPLORE_ONLY = ("inject", "seed", "pokes", "budget", "policy", "dim", "observe_pose")
RUNS_ONLY = ("estimate_path", "shape", "suggest", "window", "alpha", "max_candidates", "floor_mode", "reach",
             "cold_starts", "screen_by_fit")


def _check_modes(explore: bool):
    """One line for an option given on the command line that the mode ignores."""
    from click.core import ParameterSource

    from tacest.errors import TacestError

    ctx = click.get_current_context()
    given = [n for n in (RUNS_ONLY if explore else EXPLORE_ONLY)
             if ctx.get_parameter_source(n) == ParameterSource.COMMANDLINE]
    if given:
        names = ", ".join("--" + n.replace("_path", "").replace("_mode", "").replace("_", "-") for n in given)
        raise TacestError(f"{names}: not an option of {'--explore' if explore else 'a diagnosis of RUNS'}")


def _explore(runs, output, inject, seed, pokes, budget, policy, poke_style, effects, max_folds, fit_iterations,
             config_path, as_json, quiet, dim, observe_pose, ex):
    """``tacest diagnose --explore`` (tacest.diagnosis.explore); ex : the executor of
    --workers / --scheduler (unstarted), where each diagnosis' fits run."""
    from tacest.cli.logs import step_progress
    from tacest.diagnosis.candidates import parse_effect_list
    from tacest.diagnosis.explore import ExploreDiagnosisOptions, explore_diagnosis
    from tacest.errors import TacestError
    from tacest.io.outputs import check_output

    if runs:
        raise TacestError("--explore records its own runs: give no RUNS")
    check_output(output, inputs=[config_path], folder=True)
    if dim == 3:
        names = tuple(n.strip() for n in effects.split(",") if n.strip()) if effects else None
    else:
        names = parse_effect_list(effects) if effects else None
    opts = ExploreDiagnosisOptions(effect=inject, seed=seed, pokes=pokes, budget=budget, policy=policy,
                                   poke_style=poke_style, effects=names, max_folds=max_folds,
                                   fit_iterations=fit_iterations, config_path=config_path, dim=dim,
                                   observe_pose=observe_pose).validate()
    with ex:
        summary = explore_diagnosis(opts, output, progress=step_progress(quiet, "diagnoses"), executor=ex)
    if as_json:
        click.echo(json.dumps(summary, default=str))
    if not quiet:
        click.echo(f"verdict after {summary['steps'][-1]['actions']} actions: {summary['verdict']} "
                   f"({'decided' if summary['decided'] else 'not decided'}); wrote {output}/", err=True)


def _hint_workers(ex):
    """One information line after a diagnosis whose fits ran in this process on a
    machine with more cores (after the report: an error stays the command's one line)."""
    if not ex.distributed and machine_workers() > 1:
        logging.getLogger("tacest.diagnose").info(
            f"the fits ran in this process; --workers auto runs them on this machine's {machine_workers()} cores "
            "(docs/parallel.md)")


def _report(diag, write, out, as_json: bool, quiet: bool, extra=None):
    """Write the report folder with write(diag, out, obj) -> file names, print the JSON
    object (--json) on stdout and the verdict line on stderr (unless --quiet).  extra :
    ``extra(obj) -> writer`` of more files in the folder (write_report's ``extra``); one
    with an ``error`` attribute ends the command with it after the report is written."""
    from tacest.provenance import provenance

    obj = {**diag.to_json(), **provenance()}
    written = write(diag, out, obj) if extra is None else write(diag, out, obj, extra=extra(obj))
    if getattr(extra, "error", None) is not None:
        from tacest.errors import TacestError

        raise TacestError(f"wrote the diagnosis to {out}/, but {extra.error}")
    if as_json:
        click.echo(json.dumps(obj))
    if not quiet:
        click.echo(f"verdict: {diag.verdict} ({diag.reason}); wrote {out}/ ({', '.join(written)})", err=True)

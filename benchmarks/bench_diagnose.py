"""Benchmark ``tacest diagnose`` on simulated recordings whose effect is hidden from it.

    nice -n 10 .venv/bin/python benchmarks/bench_diagnose.py [--seeds 2] [--first-seed 0] [--effects none,latency,...]
                                                              [--design toss|effects|random] [--pairs 3]
                                                              [--pokes 3] [--tip-pokes 0]
                                                              [--cache DIR] [--timeout 1800]
                                                              [--fit-iterations 150] [--known-mass REL]
                                                              [--reach M] [--quiet] [--json OUT.json]

For every effect named in SPEC (and ``none``) and seeds FIRST..FIRST+N-1 (``--first-seed``, default 0) it records a 2-D box with
tacest's simulator and the effect at a random strength, writes it twice (with /truth
for the benchmark, without it for the diagnosis), and runs ``diagnose`` on the copy
without truth, every SPEC effect a candidate.

Designs (what the recordings contain):

``--design toss`` (default): the experiment a researcher would run to test a model
    for these effects.  A recording is ``--pairs`` (3) pairs of runs of one object: a
    toss (``tacest record --toss``: released in the air at a random height, speed and
    spin, seen flying, landing and coming to rest) and then one fast push high on the
    object where it came to rest (``effect_poke`` below, the finger parked above it
    first).  In flight only gravity, drag and the object's inertia act, so a toss shows
    a clock error (gravity appears as g/s^2), linear drag and angular damping, which
    friction and inertia absorb while a finger pushes; its landing shows restitution and
    a soft ground; the pokes show the sensor effects, com_offset, face friction and the
    ground's compliance under load.  The diagnosis holds out whole runs (fold j: runs
    j and j + 3), so every held-out fold has a toss and a poke.  The pose is observed
    (OBSERVE_POSE) and strengths are redrawn until visible (VISIBLE_D) as below.
``--design effects``: one run of ``--pokes`` fast pushes high on the object
    (``effect_poke``: 25-45 % of its height above the
    centroid, 0-10 deg above the horizontal, 3-6 cm past the first touch, an approach of
    0.15-0.3 s, i.e. 0.2-0.6 m/s): the box tips, often topples onto another face and
    lands, and slides fast; every poke is of this one kind, so every piece the held-out
    comparison holds out carries the same kinds of motion.  The object's pose is
    observed (``SimOptions.observe_pose``, SPEC /observations/pose, sigma
    OBSERVE_POSE = 0.5 mm and 0.5 mm / 5 cm in angle: motion capture or a calibrated
    camera): tactile data alone do not see the object between touches, where impacts,
    spin and coasting happen.  Effect strengths are drawn from the effect's range
    (docs/effects.md) and redrawn when the effect does not change the recording by more
    than the noise, judged from /truth only (``visibility``, VISIBLE_D): the recording
    against a clean twin (same object, same poke commands replayed, no effect).  The
    check is a necessary condition, not a sufficient one: it cannot say whether the
    plain model absorbs the change with other parameters (that is the diagnosis' job),
    and a toppling box amplifies small differences, so on this design nearly every first
    draw passes.  A slippery box slides instead of tipping, and then every effect that
    needs free motion is hidden (docs/diagnosis.md, "Measured").
``--design random``: the earlier design, ``--pokes`` random pokes of ``tacest record``
    (aimed at the centroid, 2-5 cm/s, no pose observations), the last ``--tip-pokes`` of
    them pushing high on the object (30-45 % of its height above the centroid).  Random
    pokes slide the box slowly and rarely tip it, which hides restitution, com_offset,
    angular damping, face friction and drag (docs/diagnosis.md, "Measured").

``--known-mass REL``: the object was weighed.  Every recording (clean ones too) is
diagnosed with a configuration whose mass prior is the weighed mass, the truth's mass
times exp(REL · N(0, 1)) (a weighing error of REL; seeded per recording), with
``prior.mass_log_sigma`` = REL.  Only then can a force-sensor gain be told from the mass
(``diagnose.KNOWN_MASS_LOG_SIGMA``); results are cached apart (``_km<REL>`` in their
names).

Every diagnosis runs in its own subprocess (this script with ``--worker``; its fits in
that process, or with ``--workers N`` on a local Dask cluster of N workers) under a time
limit; its result is cached as JSON per recording, and the recordings with it, in a
folder named by the code version, ``<cache>/code_<digest>`` (default cache
``$TMPDIR/tacest_bench_diagnose``; the digest is tacest.provenance.source_digest of
tacest's sources and this script), so an interrupted benchmark resumes where it stopped
and a changed line of code (a rule, a threshold, a grid, the simulator) starts a new
folder: a table is always made by one code version, printed in its header and stored
in every result (``code``) and in the summary.  Delete a folder, or a file in it, to
redo a recording.  There is no refit of single candidates into old results (that made
tables of several versions).

``--seeds``/``--first-seed``: report held-out seeds.  Seeds 0-2 of every effect and
clean seeds 0-19 were used while the rules, thresholds and the model were changed
(docs/diagnosis.md, "Tuning and held-out seeds"); a figure meant to say how the
diagnosis does on new data must come from other seeds (``--first-seed 3`` and, for clean
recordings, ``--first-seed 20``).  The summary also re-derives every verdict from the
cached held-out comparisons with the rule of this code version (``counts``): a check
that the cached verdicts are this version's (a mismatch is reported).

Printed: one line per recording (with what the object did, from its truth: largest
tilt and fastest vertex impact; an object that never tips hides restitution and
com_offset); the confusion matrix (rows: injected effect, columns:
verdict); top-1 accuracy over all recordings, without force_scale (not
identifiable without a known mass) and per effect; how often a clean
recording is blamed on an effect; the median held-out gap reduction when the right
effect is added (recordings with an effect whose candidate could be evaluated); which
candidates the estimator could not model (``unavailable``); wall times.  Then the
issue's targets with PASS / FAIL: top-1 accuracy >= 90 %, ``none`` blamed at most 1 time
in 10, median reduction >= 50 %.  The exit status is 0 whether or not they are met.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from dataclasses import dataclass, field

SPEC_EFFECTS = ("none", "restitution", "angular_damping", "linear_drag", "soft_contact", "force_bias",
                "force_scale", "latency", "face_friction", "com_offset", "time_scale")
#: effects no diagnosis can tell from "none" on these recordings: a force-sensor gain g
#: is the same data as a mass g × the true one (docs/diagnosis.md, "Identifiability")
NOT_IDENTIFIABLE = ("force_scale",)
#: random stream of the weighing error of --known-mass
WEIGHING_STREAM = 5150
#: random stream of the tipping pokes (apart from the simulator's own streams)
TIP_STREAM = 7071
#: seeds used while the diagnosis' rules, thresholds, grids and models were changed
#: (docs/diagnosis.md, "Tuning and held-out seeds"): the effect recordings of seeds 0-2
#: and the clean recordings of seeds 0-19.  Figures from them are not held out.
TUNING_SEEDS = {"effect": range(0, 3), "none": range(0, 20)}
TARGET_ACCURACY = 0.90
TARGET_NONE_BLAMED = 0.10
TARGET_REDUCTION = 0.50


def _echo(quiet):
    return (lambda *a, **k: None) if quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))


# ------------------------------------------------------------------------------------
# worker: one diagnosis in its own process


def worker(run_paths: str, fit_iterations: int, known_mass: str = "", effects: str = "", reach: str = "0",
           cold_starts: str = "", workers: str = "1") -> dict:
    """Diagnose the run files (without truth) of one recording, ``run_paths`` separated
    by RUN_SEPARATOR; never raises.  ``known_mass``: "MASS,LOG_SIGMA" (kg, -) of a
    weighed object's mass prior, or empty; ``effects``: the candidates,
    comma-separated (empty: every SPEC effect); ``reach``: noise.complementarity_reach (m);
    ``cold_starts``: DiagnoseOptions.cold_starts (empty: its default); ``workers``: a
    local Dask cluster of that many workers runs the fits (1: this process; the result
    does not depend on it, the wall time does)."""
    from tacest.diagnosis.diagnose import DiagnoseOptions, diagnose, mass_is_known
    from tacest.errors import TacestError
    from tacest.estimation.config import EstimatorConfig
    from tacest.io.run import read_run
    from tacest.parallel import Executor, ParallelSettings

    config = EstimatorConfig()
    if known_mass:
        mass, log_sigma = (float(x) for x in known_mass.split(","))
        config = config.updated({"prior": {"mass": mass, "mass_log_sigma": log_sigma}})

    runs = [read_run(p) for p in run_paths.split(RUN_SEPARATOR)]
    assert all(r.truth is None for r in runs), "the diagnosed copies must not carry /truth"
    t0 = time.perf_counter()
    try:
        opts = DiagnoseOptions(fit_iterations=fit_iterations, reach=float(reach))
        if cold_starts:
            opts.cold_starts = cold_starts
        if effects:
            opts.effects = tuple(effects.split(","))
        with Executor(ParallelSettings(workers=int(workers))) as ex:
            d = diagnose(runs, "box", config=config, options=opts, executor=ex)
    except TacestError as exc:
        return {"ok": False, "error": f"{type(exc).__name__}: {exc}", "wall": time.perf_counter() - t0}
    except Exception as exc:  # noqa: BLE001 - a crash is a result to report
        return {"ok": False, "error": f"crash: {type(exc).__name__}: {exc}", "wall": time.perf_counter() - t0}
    obj = d.to_json()
    return {"ok": True, "verdict": obj["verdict"], "reason": obj["reason"], "effects": obj["effects"],
            "where": obj["where"][:10], "heldout": obj["heldout"], "backend": obj["backend"],
            "wall": time.perf_counter() - t0, "samples": sum(r.n_samples for r in runs), "runs": len(runs),
            "mass_known": mass_is_known(config), "code": code_version(), "workers": int(workers)}


#: separates the run files of one recording on the worker's command line
RUN_SEPARATOR = "::"


def run_job(run_paths: list, fit_iterations: int, timeout: float, known_mass: str = "", effects: str = "",
            reach: float = 0.0, cold_starts: str = "", workers: int = 1) -> dict:
    """The worker's result for the run files ``run_paths`` (one recording), in a subprocess
    with a time limit."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", RUN_SEPARATOR.join(map(str, run_paths)),
           str(fit_iterations), known_mass, effects, repr(float(reach)), cold_starts or "", str(int(workers))]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"ok": False, "error": f"timeout: no result within {timeout:.0f} s", "wall": time.perf_counter() - t0}
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {"ok": False, "error": f"worker exit {proc.returncode}: {tail}", "wall": time.perf_counter() - t0}
    return json.loads(lines[-1])


# ------------------------------------------------------------------------------------
# recordings


@dataclass
class Recording:
    """One benchmark recording: the run files diagnosed together (without /truth), their
    twins with /truth, the injected effect ({"name": ..., params...}), the file-name tag
    of its design, and the strength draws (``visibility``) where the design checks them."""

    bare: list
    truth: list
    injected: dict
    tag: str
    draw: dict = field(default=None)


def _injected(truth_path: Path) -> dict:
    from tacest.io.run import read_run

    truth = read_run(truth_path).truth.effects
    injected = truth[0] if isinstance(truth, list) and truth else (truth if isinstance(truth, dict) else {"name": "none"})
    return injected if injected.get("name") is not None else {"name": "none"}


#: tipping pokes (--tip-pokes): aimed this fraction of the object's height above its
#: centroid, this many degrees above the horizontal, this far (m) past the first touch;
#: they tip a box on a grippy ground by 25-40 deg (seeds 0 and 2, ground friction 0.77)
#: and slide a slippery one (seeds 1 and 3: 0-4 deg), measured on the truth
TIP_HEIGHT = (0.30, 0.45)
TIP_ANGLE_DEG = (0.0, 10.0)
TIP_DEPTH = (0.03, 0.06)


def high_poke(rng: np.random.Generator, state, angle_deg, height, depth) -> tuple:
    """(approach angle rad, target (2,) m, depth m) of a poke from a random side aimed
    above the centroid of the object of a WorldState: elevation drawn from ``angle_deg``
    (deg), target height from ``height`` (fractions of the object's height above its
    centroid), depth from ``depth`` (m)."""
    world = state.world()
    c, verts = world.centroid__world(), world.vertices__world()
    h = float(np.ptp(verts[:, 1]))
    angle = math.radians(rng.uniform(*angle_deg))
    if rng.random() < 0.5:
        angle = math.pi - angle
    target = c + np.array([0.0, rng.uniform(*height) * h])
    return angle, target, float(rng.uniform(*depth))


def tip_poke(rng: np.random.Generator, state) -> np.ndarray:
    """A tipping poke (POKE_NAMES vector) at the object of a WorldState, from a random side."""
    from tacest.sim.pokes import APPROACH_TIME, CLEARANCE

    angle, target, depth = high_poke(rng, state, TIP_ANGLE_DEG, TIP_HEIGHT, TIP_DEPTH)
    return np.array([0.0, angle, target[0], target[1], depth, (CLEARANCE + depth) / APPROACH_TIME])


def record(effect: str, seed: int, pokes: int, folder: Path, tip: int = 0) -> Recording:
    """Record (or reuse) the random-design recording of ``effect`` and ``seed``.  With ``tip``
    > 0 the last ``tip`` of the ``pokes`` are tipping pokes (tip_poke), the first ones the
    random pokes of ``tacest record``; the files are named ``..._tip<N>``."""
    from tacest.io.run import write_run
    from tacest.sim.record import SimOptions, record_sim, simulate_aimed_pokes

    tag = f"_tip{tip}" if tip else ""
    full = folder / f"{effect}_{seed}{tag}_truth.h5"
    bare = folder / f"{effect}_{seed}{tag}.h5"
    if not (full.exists() and bare.exists()):
        opts = SimOptions(object_spec="box", seed=seed, pokes=pokes - tip,
                          effects=[] if effect == "none" else [effect])
        rng = np.random.default_rng([seed, TIP_STREAM])
        run = simulate_aimed_pokes(lambda i, st: tip_poke(rng, st), tip, opts, run=record_sim(opts))
        write_run(run, full)
        write_run(run, bare, include_truth=False)
    return Recording([bare], [full], _injected(full), tag)


#: the "effects" design (--design effects, the default): every poke of a recording is
#: one kind, a fast push high on the object, so that every piece the held-out comparison
#: holds out carries the effects of tipping, landing and sliding fast: aimed this
#: fraction of the object's height above its centroid, this many degrees above the
#: horizontal, this far (m) past the first touch, with an approach of this many seconds
#: (0.2-0.5 m/s instead of the random pokes' 2-5 cm/s)
DESIGN_STREAM = 7072
EFFECT_POKE_HEIGHT = (0.25, 0.45)
EFFECT_POKE_ANGLE_DEG = (0.0, 10.0)
EFFECT_POKE_DEPTH = (0.03, 0.06)
EFFECT_POKE_DURATION = (0.15, 0.3)
#: m, the object pose observed as by motion capture or a calibrated camera (SPEC
#: /observations/pose; the angle sigma is this over tacest.sim.record.POSE_ANGLE_LEVER)
OBSERVE_POSE = 5e-4
#: visibility of an injected effect (from /truth only): D = sum over samples of the mean
#: squared displacement of the object's vertices against a clean twin (same object, same
#: poke commands, no effect) in units of the pose sigma, plus the squared change of the
#: force stream in units of the force sigma; 0.5 D is the log-likelihood ratio the data
#: would carry against "no effect" if nothing else were refitted.  A draw counts as
#: visible when 0.5 D is at least 30 times one parameter's BIC penalty (0.5 ln N, about
#: 3.5 for N ~ 1000 held-out samples), i.e. D >= VISIBLE_D; a strength that is not
#: visible is redrawn from the effect's own range (up to MAX_DRAWS draws; the last draw
#: is kept and marked when none is visible).  The clock effect (time_scale) changes no
#: stream, only /time, so it is not checked.
VISIBLE_D = 200.0
MAX_DRAWS = 5
#: random stream of the redraws of an effect's strength
REDRAW_STREAM = 7073


def effect_poke(rng: np.random.Generator, state) -> np.ndarray:
    """A fast poke high on the object (POKE_NAMES vector) from a random side."""
    from tacest.sim.pokes import CLEARANCE

    angle, target, depth = high_poke(rng, state, EFFECT_POKE_ANGLE_DEG, EFFECT_POKE_HEIGHT, EFFECT_POKE_DEPTH)
    speed = min(1.0, (CLEARANCE + depth) / rng.uniform(*EFFECT_POKE_DURATION))
    return np.array([0.0, angle, target[0], target[1], depth, speed])


def _object_context(opts):
    """The EffectContext of the object record_sim makes from ``opts`` (the same draws)."""
    from tacest.sim import effects as fx
    from tacest.sim.objects import inradius, make_shape, uniform_object
    from tacest.sim.record import _rng, _STREAM_OBJECT

    rng = _rng(opts.seed, _STREAM_OBJECT)
    vertices, kind, _ = make_shape(opts.object_spec, rng)
    obj = uniform_object(vertices, kind, rng)
    return fx.EffectContext(mass=obj.mass, inertia=obj.inertia, inradius=inradius(vertices), n_faces=obj.n_faces,
                            friction_ground=obj.friction_ground)


def simulate_design(opts, pokes: int, seed: int, actions=None):
    """A recording of ``pokes`` effect pokes (each aimed at the object as it is then), or
    of the given poke vectors replayed as commanded (the clean twin); returns the Run."""
    from tacest.sim.record import initial_state, simulate_aimed_pokes

    rng = np.random.default_rng([seed, DESIGN_STREAM])
    aim = (lambda i, st: effect_poke(rng, st)) if actions is None else (lambda i, st: actions[i])
    return simulate_aimed_pokes(aim, pokes, opts, state=initial_state(opts))


def visibility(run, twin) -> float:
    """D of a recording against its clean twin (see VISIBLE_D), from /truth and the
    streams; poke segments are compared sample by sample over their common length (a
    run without pokes, a toss: the whole run)."""
    from tacest.geometry.transforms import rot2

    def verts(r, i):
        P = r.truth.pose[i]
        return (np.asarray(r.truth.vertices) @ rot2(P[2]).T) + P[:2]

    sig_p = OBSERVE_POSE
    sig_f = float(np.asarray(run.extra_attrs.get("noise_force", 0.02)))
    D = 0.0
    pairs = list(zip(run.actions.segments, twin.actions.segments))
    if not len(run.actions.segments):
        pairs = [((0, run.n_samples), (0, twin.n_samples))]
    for (a, b), (c, d) in pairs:
        n = min(b - a, d - c)
        for k in range(n):
            dv = verts(run, a + k) - verts(twin, c + k)
            D += float(np.mean(np.sum(dv ** 2, axis=1))) / sig_p ** 2
        if run.force is not None and twin.force is not None:
            df = np.nan_to_num(np.asarray(run.force[a:a + n]) - np.asarray(twin.force[c:c + n]))
            D += float(np.sum(df ** 2)) / sig_f ** 2
    return D


def record_visible(effect: str, seed: int, simulate) -> tuple:
    """(runs, draw info) of ``effect`` on the box of ``seed`` (pose observed): the
    effect's strength drawn from its range and redrawn (up to MAX_DRAWS draws) until the
    recording differs from its clean twin by VISIBLE_D (``visibility``, summed over the
    runs); info {"visibility": D, "draws": n, "visible": bool}.  ``simulate(opts,
    replay)`` -> (runs, commands) records a design with SimOptions ``opts``, replaying
    the commands it returned for the twin (``replay`` None: a new recording)."""
    from tacest.sim import effects as fx
    from tacest.sim.record import SimOptions

    base = SimOptions(object_spec="box", seed=seed, pokes=0, observe_pose=OBSERVE_POSE)
    info = {"visibility": None, "draws": 0, "visible": True}
    if effect == "none":
        return simulate(base, None)[0], info
    ctx = _object_context(base)
    for draw in range(MAX_DRAWS):
        eff = (effect if draw == 0 else
               fx.resolve_effect(effect, {}, np.random.default_rng([seed, REDRAW_STREAM, draw]), ctx))
        runs, commands = simulate(SimOptions(**{**base.__dict__, "effects": [eff]}), None)
        info["draws"] = draw + 1
        if effect == "time_scale":  # changes no stream, only /time
            info["visibility"], info["visible"] = None, True
            break
        twins, _ = simulate(base, commands)
        D = sum(visibility(r, t) for r, t in zip(runs, twins))
        info["visibility"], info["visible"] = D, D >= VISIBLE_D
        if info["visible"]:
            break
    return runs, info


def record_design(effect: str, seed: int, pokes: int, folder: Path) -> Recording:
    """Record (or reuse) an "effects"-design recording (its draw: {"visibility": D,
    "draws": n, "visible": bool})."""
    from tacest.io.run import write_run

    full = folder / f"{effect}_{seed}_design_truth.h5"
    bare = folder / f"{effect}_{seed}_design.h5"
    meta = folder / f"{effect}_{seed}_design_draw.json"
    if not (full.exists() and bare.exists() and meta.exists()):
        def simulate(opts, replay):
            run = simulate_design(opts, pokes, seed, actions=replay)
            return [run], run.actions.params

        (run,), info = record_visible(effect, seed, simulate)
        write_run(run, full)
        write_run(run, bare, include_truth=False)
        meta.write_text(json.dumps(info))
    return Recording([bare], [full], _injected(full), "_design", json.loads(meta.read_text()))


#: the "toss" design (--design toss): TOSS_PAIRS pairs of runs, each a toss (the
#: object released in the air at a random height, speed and spin, tacest.sim.record's
#: TOSS_* ranges, seen landing and coming to rest) and then one effect poke at the
#: object where it came to rest, the finger parked above it first; the release is
#: always over x = 0, so that the clean twin replays the same tosses
TOSS_PAIRS = 3
#: random stream of the tosses' releases
TOSS_STREAM = 7074


def simulate_toss_design(opts, pairs: int, seed: int, replay=None) -> tuple:
    """(runs, pokes): the 2 × ``pairs`` runs of a toss-design recording (toss, poke,
    toss, poke, ...) and the poke vectors (pairs, 6); with ``replay`` (pokes as
    returned) those pokes are replayed as commanded (the clean twin)."""
    from tacest.geometry.transforms import rot2
    from tacest.sim.record import initial_state, park_fingers, simulate_pokes, state_from_run, toss_state

    rng_toss = np.random.default_rng([seed, TOSS_STREAM])
    rng_poke = np.random.default_rng([seed, DESIGN_STREAM])
    state = initial_state(opts)
    runs, pokes = [], []
    for i in range(pairs):
        tossed = toss_state(state, rng_toss, x=0.0)
        toss_run = simulate_pokes(tossed, np.zeros((0, 6)), opts, noise_key=2 * i + 1, settle_first=True)
        st = state_from_run(toss_run)
        top = float(np.max((st.obj.vertices @ rot2(st.pose[2]).T)[:, 1])) + float(st.pose[1])
        st.p_finger__world = park_fingers(float(st.pose[0]), top, st.n_fingers, float(np.max(st.finger_radius)))
        poke = effect_poke(rng_poke, st) if replay is None else np.asarray(replay[i], float)
        poke_run = simulate_pokes(st, poke[None], opts, noise_key=2 * i + 2)
        runs += [toss_run, poke_run]
        pokes.append(poke)
        state = state_from_run(poke_run)
    return runs, np.array(pokes)


def record_toss_design(effect: str, seed: int, pairs: int, folder: Path) -> Recording:
    """Record (or reuse) a "toss"-design recording: 2 × ``pairs`` run files, strengths
    redrawn until visible against the clean twin as in the "effects" design."""
    from tacest.io.run import write_run

    n = 2 * pairs
    stem = f"{effect}_{seed}_toss{pairs}"
    full = [folder / f"{stem}_{i}_truth.h5" for i in range(n)]
    bare = [folder / f"{stem}_{i}.h5" for i in range(n)]
    meta = folder / f"{stem}_draw.json"
    if not (all(p.exists() for p in full + bare) and meta.exists()):
        runs, info = record_visible(effect, seed, lambda opts, replay: simulate_toss_design(opts, pairs, seed, replay))
        for run, f, b in zip(runs, full, bare):
            write_run(run, f)
            write_run(run, b, include_truth=False)
        meta.write_text(json.dumps(info))
    return Recording(bare, full, _injected(full[0]), f"_toss{pairs}", json.loads(meta.read_text()))


def weighed_mass(rec: Recording, effect: str, seed: int, rel: float) -> str:
    """"MASS,LOG_SIGMA" of --known-mass: the truth's mass times exp(rel · N(0, 1)), a
    weighing error drawn per recording (seeded by effect and seed), and rel."""
    from tacest.io.run import read_run

    if not rel > 0:
        raise SystemExit("--known-mass must be > 0")
    m = float(read_run(rec.truth[0]).truth.mass)
    rng = np.random.default_rng([seed, SPEC_EFFECTS.index(effect), WEIGHING_STREAM])
    return f"{m * math.exp(rel * rng.normal()):.6g},{rel:g}"


def truth_motion(rec: Recording) -> dict:
    """What the object did in the recording (from its /truth, never shown to the
    diagnosis): the largest tilt from its start angle (deg) and the fastest approach of a
    vertex arriving at the ground (m/s; an impact, where restitution could show).  Where
    the object never tips, restitution, com_offset and most of angular_damping leave no
    trace in the data."""
    from tacest.io.run import read_run

    tilt, speed = 0.0, 0.0
    for path in rec.truth:
        run = read_run(path)
        tr = run.truth
        P, V = np.asarray(tr.pose, float), np.asarray(tr.vertices, float)
        c, s = np.cos(P[:, 2]), np.sin(P[:, 2])
        y = P[:, 1:2] + s[:, None] * V[None, :, 0] + c[:, None] * V[None, :, 1]  # (T, K) m, world height
        vy = np.diff(y, axis=0) / run.dt  # m/s (a time_scale recording's dt is off by a few %)
        arriving = y[1:] - y[1:].min() < IMPACT_HEIGHT  # at the ground (the lowest any vertex goes) at the end of the interval
        speed = max(speed, float(np.max(-vy[arriving], initial=0.0)))
        if run.actions is not None and len(run.actions.segments):  # a toss's tumbling is not a tilt
            tilt = max(tilt, float(np.degrees(np.max(np.abs(P[:, 2] - P[0, 2])))))
    return {"tilt_deg": tilt, "impact_speed": max(speed, 0.0)}


#: m: a vertex this close to the lowest height seen counts as at the ground (truth_motion)
IMPACT_HEIGHT = 1e-3


def tacest_location() -> str:
    """Where tacest is imported from (a worktree or an installed copy)."""
    import tacest

    return str(Path(tacest.__file__).resolve().parent)


def code_version() -> str:
    """The code version of the results: tacest.provenance.source_digest of tacest's
    sources and of this script (its designs and the diagnosis options of its worker)."""
    from tacest.provenance import source_digest

    return source_digest(Path(__file__).resolve())


# ------------------------------------------------------------------------------------
# summary


def _median(values):
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(vals)) if vals else math.nan


def _reduction(c: dict) -> float:
    """Share of the held-out gap a candidate closed, as diagnose defines it (capped at 1),
    and 0 when the plain model had no gap above the floor (nothing was closed)."""
    before, improvement = c.get("gap_before"), c.get("improvement")
    if before is None or improvement is None or not before > 0:
        return 0.0
    return min(1.0, improvement / before)


def rederive_verdict(r: dict) -> str:
    """The verdict of a cached result under the current rule
    (tacest.diagnosis.diagnose.counts) from its stored held-out comparisons: the fits
    are the same, only the decision may have changed since the result was cached."""
    from tacest.diagnosis.diagnose import SOFT_CONTACT_MATERIAL_SINK, counts, params_immaterial

    best, best_score = "none", -math.inf
    held = r.get("heldout") or {}
    for e in r.get("effects", []):
        if e.get("status") != "ok":
            continue
        # results cached before candidates stored their floor: the held-out floor of all
        # folds, which is theirs when they were compared on every fold
        floor = e.get("floor", held.get("floor") if e.get("folds_compared") == held.get("folds_valid") else None)
        if counts(e.get("score"), e.get("folds_improved"), e.get("folds_compared"), e.get("gap_before"),
                  e.get("improvement"), floor, e.get("at_bound") or (), e.get("name"),
                  immaterial=params_immaterial(e.get("params") or {}, mass=e.get("fit_mass"),
                                               material_sink=held.get("material_sink", SOFT_CONTACT_MATERIAL_SINK)),
                  mass_known=bool(r.get("mass_known"))) and e["score"] > best_score:
            best, best_score = e["name"], e["score"]
    return best


def summarize(results: list) -> dict:
    # the cache is per code version: every verdict is the diagnosis' own; re-deriving it
    # from the stored comparisons with this version's rule is a check (a mismatch means
    # the stored comparisons do not carry what the rule reads)
    mismatched = [f"{r['effect']} seed {r['seed']}: {r['verdict']} (re-derived: {rederive_verdict(r)})"
                  for r in results if r.get("ok") and rederive_verdict(r) != r["verdict"]]
    codes = sorted({str(r.get("code")) for r in results})
    tuned = sorted({f"{r['effect']} {r['seed']}" for r in results
                    if r["seed"] in TUNING_SEEDS["none" if r["effect"] == "none" else "effect"]})
    ok = [r for r in results if r.get("ok")]
    names = list(SPEC_EFFECTS)
    conf = {t: {p: 0 for p in names + ["failed"]} for t in names}
    for r in results:
        conf[r["effect"]][r["verdict"] if r.get("ok") else "failed"] += 1
    correct = sum(1 for r in ok if r["verdict"] == r["effect"])
    per_effect = {}
    for t in names:
        rs = [r for r in results if r["effect"] == t]
        if rs:
            per_effect[t] = sum(1 for r in rs if r.get("ok") and r["verdict"] == t) / len(rs)
    nones = [r for r in results if r["effect"] == "none"]
    blamed = sum(1 for r in nones if not r.get("ok") or r["verdict"] != "none")
    reductions = []
    for r in ok:
        if r["effect"] == "none":
            continue
        c = next((e for e in r["effects"] if e["name"] == r["effect"]), None)
        if c is not None and c.get("status") == "ok":
            reductions.append(_reduction(c))
        elif c is not None and c.get("status") == "screened" and c.get("full_improvement") is not None:
            reductions.append(0.0)  # not held out: its fit to all data beat no penalty, it closed nothing
    # force_scale is observationally equivalent to a clean recording of an object g times
    # as heavy (only gain x mass is identifiable): the accuracy without it says how the
    # diagnosis does on what the data can tell (reported beside the figure, not instead)
    rest = [r for r in results if r["effect"] not in NOT_IDENTIFIABLE]
    accuracy_identifiable = (sum(1 for r in rest if r.get("ok") and r["verdict"] == r["effect"]) / len(rest)
                             if rest else math.nan)
    unavailable = sorted({e["name"] for r in ok for e in r["effects"] if e.get("status") == "unavailable"})
    return {
        "recordings": len(results), "failures": len(results) - len(ok), "confusion": conf,
        "accuracy": correct / len(results) if results else math.nan, "accuracy_per_effect": per_effect,
        "accuracy_identifiable": accuracy_identifiable,
        "none_recordings": len(nones), "none_blamed": blamed, "none_blamed_rate": blamed / len(nones) if nones else math.nan,
        "median_reduction_right_effect": _median(reductions), "reductions_right_effect": reductions,
        "unavailable_candidates": unavailable,
        "mass_known": bool(ok) and all(r.get("mass_known") for r in ok),
        "wall_median": _median([r.get("wall") for r in results]), "wall_max": max([r.get("wall", 0) for r in results] or [0]),
        "codes": codes, "verdicts_not_rederived": mismatched, "tuning_recordings": tuned,
    }


def print_summary(s: dict):
    names = list(SPEC_EFFECTS)
    short = {n: n[:6] for n in names}
    short.update({"angular_damping": "angdmp", "linear_drag": "lindrg", "soft_contact": "soft", "force_bias": "fbias",
                  "force_scale": "fscale", "face_friction": "facefr", "com_offset": "com", "time_scale": "tscale",
                  "restitution": "restit", "latency": "latncy"})
    cols = names + ["failed"]
    print("\nconfusion matrix (rows: injected effect, columns: verdict)")
    print(f"{'':>16}" + "".join(f"{short.get(c, c):>8}" for c in cols))
    for t in names:
        row = s["confusion"][t]
        if sum(row.values()) == 0:
            continue
        print(f"{t:>16}" + "".join(f"{row[c]:>8}" for c in cols))
    print(f"\nrecordings {s['recordings']}, failed diagnoses {s['failures']}; code version(s) "
          f"{', '.join(s['codes'])}" + ("" if len(s["codes"]) == 1 else "  -- MIXED: not one table"))
    if s["tuning_recordings"]:
        print(f"NOT HELD OUT: {len(s['tuning_recordings'])} recording(s) of seeds used for tuning "
              f"(TUNING_SEEDS): {', '.join(s['tuning_recordings'][:8])}"
              + (" ..." if len(s["tuning_recordings"]) > 8 else ""))
    else:
        print("held out: no recording of a seed used for tuning")
    for m in s["verdicts_not_rederived"]:
        print(f"  WARNING verdict differs from the rule's re-derivation: {m}")
    print(f"top-1 accuracy without {', '.join(NOT_IDENTIFIABLE)} (not identifiable without a known mass"
          + ("; here the mass was known" if s.get("mass_known") else "") + f"): {s['accuracy_identifiable']:.0%}")
    print("top-1 accuracy per effect: " + ", ".join(f"{k} {v:.0%}" for k, v in s["accuracy_per_effect"].items()))
    print(f"candidates the estimator could not model: {', '.join(s['unavailable_candidates']) or 'none'}")
    red = s["reductions_right_effect"]
    print(f"held-out gap reduction with the right effect: {len(red)} recordings, "
          + ", ".join(f"{x:.0%}" for x in red))
    print(f"wall time per diagnosis: median {s['wall_median']:.0f} s, max {s['wall_max']:.0f} s")
    print("\ntargets")
    for label, value, ok in (
            ("top-1 accuracy >= 90 %", f"{s['accuracy']:.0%}", s["accuracy"] >= TARGET_ACCURACY),
            ("none blamed <= 1 in 10", f"{s['none_blamed']}/{s['none_recordings']}",
             s["none_blamed_rate"] <= TARGET_NONE_BLAMED),
            ("median reduction >= 50 %", f"{s['median_reduction_right_effect']:.0%}"
             if np.isfinite(s["median_reduction_right_effect"]) else "n/a",
             s["median_reduction_right_effect"] >= TARGET_REDUCTION)):
        print(f"  {'PASS' if ok else 'FAIL'}  {label}: {value}")


def main(argv=None):
    from tacest.diagnosis.diagnose import COLD_STARTS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", nargs=7, help=argparse.SUPPRESS)
    ap.add_argument("--seeds", type=int, default=2, help="seeds 0..N-1 per effect (default 2)")
    ap.add_argument("--first-seed", type=int, default=0,
                    help="seeds FIRST..FIRST+N-1 (default 0; e.g. calibration on seeds not reported)")
    ap.add_argument("--effects", default=",".join(SPEC_EFFECTS), help="effects to record (default: all of SPEC)")
    ap.add_argument("--design", choices=("toss", "effects", "random"), default="toss",
                    help="toss: --pairs pairs of runs, a toss and a fast high poke, pose observed, effect "
                         "strengths visible against a clean twin (default); effects: one run of --pokes fast "
                         "high pokes, pose observed; random: the random pokes of tacest record, with --tip-pokes")
    ap.add_argument("--pairs", type=int, default=TOSS_PAIRS,
                    help=f"toss design: pairs of runs (toss, poke) per recording (default {TOSS_PAIRS})")
    ap.add_argument("--pokes", type=int, default=3, help="effects and random designs: pokes per recording (default 3)")
    ap.add_argument("--tip-pokes", type=int, default=0,
                    help="random design: how many of the pokes (the last ones) push high to tip the object (default 0)")
    ap.add_argument("--cache", default=None, help="folder of recordings and cached results")
    ap.add_argument("--timeout", type=float, default=1800.0, help="s per diagnosis (default 1800)")
    ap.add_argument("--fit-iterations", type=int, default=150, help="IPOPT iterations per stage (default 150)")
    ap.add_argument("--known-mass", type=float, default=None, metavar="REL",
                    help="diagnose with the weighed mass (truth x exp(REL N(0,1))) as a prior of log sigma REL")
    ap.add_argument("--reach", type=float, default=None, metavar="M",
                    help="noise.complementarity_reach of the diagnoses (m; 0: off; default: the diagnosis' "
                         "default, DiagnoseOptions.reach); results with a reach are cached apart (_reach<M>)")
    ap.add_argument("--cold-starts", default="", choices=("", *COLD_STARTS),
                    help="which candidates also start from the estimator's own starts (DiagnoseOptions.cold_starts; "
                         "default: the diagnosis' default); results with it given are cached apart (_cold-<MODE>)")
    ap.add_argument("--workers", type=int, default=1,
                    help="fits of each diagnosis on a local Dask cluster of this many workers (default 1: in the "
                         "diagnosis' process, as tacest diagnose; the verdicts do not depend on it, the wall times do)")
    ap.add_argument("--quiet", action="store_true")
    ap.add_argument("--json", default=None, help="write every result and the summary to this file")
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker[0], int(args.worker[1]), *args.worker[2:])))
        return 0
    effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    bad = [e for e in effects if e not in SPEC_EFFECTS]
    if args.design != "random" and args.tip_pokes:
        print("--tip-pokes belongs to --design random (every poke of the other designs pushes high)",
              file=sys.stderr)
        return 1
    if args.design == "toss" and args.pairs < 2:
        print("--pairs must be >= 2 (every run is held out once)", file=sys.stderr)
        return 1
    if args.reach is None:
        from tacest.diagnosis.diagnose import DiagnoseOptions

        args.reach = DiagnoseOptions().reach
    if not args.reach >= 0:
        print(f"--reach must be >= 0 (m), got {args.reach}", file=sys.stderr)
        return 1
    if args.workers < 1:
        print(f"--workers must be >= 1, got {args.workers}", file=sys.stderr)
        return 1
    if bad or args.seeds < 1 or args.pokes < 2 or not 0 <= args.tip_pokes < args.pokes:
        print(f"bad arguments: effects {bad}, seeds {args.seeds}, pokes {args.pokes} (>= 2), "
              f"tip pokes {args.tip_pokes} (0 <= tip < pokes)", file=sys.stderr)
        return 1
    echo = _echo(args.quiet)
    code = code_version()
    cache = Path(args.cache or Path(tempfile.gettempdir()) / "tacest_bench_diagnose") / f"code_{code}"
    cache.mkdir(parents=True, exist_ok=True)
    design = {"toss": f"{args.pairs} pairs of runs (a toss, a fast high poke) each, pose observed at "
                      f"{OBSERVE_POSE * 1e3:g} mm",
              "effects": f"{args.pokes} fast high pokes each, pose observed at {OBSERVE_POSE * 1e3:g} mm",
              "random": f"{args.pokes} random pokes each ({args.tip_pokes} tipping)"}[args.design]
    print(f"load average {os.getloadavg()[0]:.2f}; cache {cache}; {len(effects)} effects x {args.seeds} seeds, "
          f"{design}; code {code} (tacest {tacest_location()})", flush=True)
    results = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for effect in effects:
            if args.design == "toss":
                rec = record_toss_design(effect, seed, args.pairs, cache)
            elif args.design == "effects":
                rec = record_design(effect, seed, args.pokes, cache)
            else:
                rec = record(effect, seed, args.pokes, cache, args.tip_pokes)
            draw, injected = rec.draw, rec.injected
            known = ""
            if args.known_mass is not None:
                known = weighed_mass(rec, effect, seed, args.known_mass)
            out = cache / (f"{effect}_{seed}{rec.tag}{'' if not known else f'_km{args.known_mass:g}'}"
                           f"{'' if not args.reach else f'_reach{args.reach:g}'}"
                           f"{'' if not args.cold_starts else f'_cold-{args.cold_starts}'}"
                           f"{'' if args.workers == 1 else f'_w{args.workers}'}.json")
            if out.exists():
                res = json.loads(out.read_text())
            else:
                echo(f"diagnosing {rec.bare[0].stem}{'' if len(rec.bare) == 1 else f' and {len(rec.bare) - 1} more runs'}"
                     " ..." + (f" (weighed mass, log sigma {args.known_mass:g})" if known else ""))
                res = run_job(rec.bare, args.fit_iterations, args.timeout, known, "", args.reach, args.cold_starts,
                              args.workers)
                # the worker's own "code" is kept: a result whose code differs from this
                # run's (the tree edited while the benchmark ran) makes the table MIXED
                res.update(effect=effect, seed=seed, injected=injected)
                res.setdefault("code", code)
                out.write_text(json.dumps(res))
            results.append(res)
            verdict = res["verdict"] if res.get("ok") else "FAILED"
            right = next((e for e in res.get("effects", []) if e["name"] == effect), None)
            extra = ""
            if right is not None and right.get("status") == "ok":
                extra = f", {effect}: reduction {_reduction(right):.0%}, params {right['params']}"
            elif right is not None:
                extra = f", {effect}: {right.get('status')}"
            mot = truth_motion(rec)
            res["motion"] = mot
            extra += f", truth: tilt {mot['tilt_deg']:.1f} deg, impacts up to {mot['impact_speed']:.2f} m/s"
            if draw is not None and effect != "none":
                res["draw"] = draw
                extra += (f", visibility D {draw['visibility']:.3g}" if draw["visibility"] is not None else "") \
                    + f" (draw {draw['draws']}{'' if draw['visible'] else ', NOT visible'})"
            print(f"{effect:>16} seed {seed}: verdict {verdict:<16} ({res.get('wall', math.nan):.0f} s{extra})"
                  + ("" if res.get("ok") else f" -- {res.get('error')}"), flush=True)
    s = summarize(results)
    s["code"] = code
    s["seeds"] = [args.first_seed, args.first_seed + args.seeds - 1]
    print_summary(s)
    if args.json:
        Path(args.json).write_text(json.dumps({"results": results, "summary": s}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Many objects at once: ``tacest estimate --batch MANIFEST -o DIR`` (docs/parallel.md).

A manifest says which run files belong to which object:

- CSV (``.csv``), one row per run file, a header naming the columns ``object`` and
  ``run`` and optionally ``shape`` (the object's shape parameterization; it must be the
  same on each of its rows)::

      object,run,shape
      mug,mug_1.h5,polygon:8
      mug,mug_2.h5,polygon:8
      box,box_1.h5,

- TOML (``.toml``), one table per object under ``objects``, with ``runs`` (a list of
  paths) and optionally ``shape``::

      [objects.mug]
      runs = ["mug_1.h5", "mug_2.h5"]
      shape = "polygon:8"

Paths are relative to the manifest's folder.  An object's name names its estimate file
(``NAME.h5``): letters, digits, ``_``, ``-`` and ``.``, starting with a letter or digit.
A manifest with an unknown column or key, no object, an object without runs, a missing
run file, a run listed twice (under one object or two), or a name given twice is an
error before any work (one line, exit status 2).

Every object is one task of the executor (tacest.parallel): the client reads and checks
its runs, the task estimates it (tacest.dims.estimate_runs) where it runs.  An object
whose runs cannot be read or whose estimate fails is listed with its one-line reason;
it never stops the others and is never dropped.  The output folder holds ``NAME.h5`` of
every estimated object and the summary, ``summary.csv`` and ``summary.json``
(:data:`SUMMARY_COLUMNS`), written at once when every task is done (tacest.io.outputs
.atomic_dir): an interrupted batch leaves no partial output.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import re
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from tacest.errors import TacestError

log = logging.getLogger(__name__)

#: an object's name: its estimate file is NAME.h5
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
#: columns of a CSV manifest (``object`` and ``run`` required)
CSV_COLUMNS = ("object", "run", "shape")
#: keys of an object's table in a TOML manifest (``runs`` required)
TOML_KEYS = ("runs", "shape")
#: the file that marks a folder as a batch output (atomic_dir's marker)
SUMMARY_JSON = "summary.json"
SUMMARY_CSV = "summary.csv"
#: columns of summary.csv (and keys of each object in summary.json)
SUMMARY_COLUMNS = ("object", "status", "reason", "estimate", "runs", "shape", "solver_status", "iterations",
                   "wall_time", "objective", "mass", "friction_ground", "friction_finger", "fit_consistent")


@dataclass(frozen=True)
class BatchObject:
    """One object of a manifest: its name, its run files (paths as the manifest resolves
    them) and its shape (None: the command's --shape)."""

    name: str
    runs: tuple
    shape: Optional[str] = None


@dataclass
class BatchResult:
    """One object's outcome: ``status`` ``ok`` (``estimate`` set) or ``failed``
    (``reason``: one line); seconds: its task's compute time."""

    name: str
    runs: tuple
    shape: str
    status: str
    reason: str = ""
    estimate: object = None
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)


def read_manifest(path) -> list:
    """The objects of a manifest (module doc), in the order of their first row or table;
    TacestError (one line naming the manifest) for a manifest that is not valid."""
    path = Path(path)
    if not path.is_file():
        raise TacestError(f"{path}: no such manifest file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        entries = _read_csv(path)
    elif suffix == ".toml":
        entries = _read_toml(path)
    else:
        raise TacestError(f"{path}: a manifest is a .csv or a .toml file (docs/parallel.md)")
    if not entries:
        raise TacestError(f"{path}: lists no object")
    seen_runs = {}
    objects = []
    for name, (runs, shape) in entries.items():
        if not NAME_PATTERN.match(name):
            raise TacestError(f"{path}: object name {name!r} cannot name a file (letters, digits, '_', '-', '.', "
                              "starting with a letter or digit)")
        if not runs:
            raise TacestError(f"{path}: object {name!r} has no run file")
        resolved = []
        for run in runs:
            p = Path(run) if Path(run).is_absolute() else path.parent / run
            key = p.resolve()
            if key in seen_runs:
                raise TacestError(f"{path}: run {run} is listed twice (object {seen_runs[key]!r} and {name!r}); "
                                  "each run file belongs to one object, once")
            seen_runs[key] = name
            if not p.is_file():
                raise TacestError(f"{path}: object {name!r}: run file {p} does not exist")
            resolved.append(str(p))
        objects.append(BatchObject(name=name, runs=tuple(resolved), shape=shape or None))
    return objects


def _read_csv(path: Path) -> dict:
    """{name: ([run, ...], shape or None)} of a CSV manifest."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise TacestError(f"{path}: cannot read the manifest ({exc.__class__.__name__}: {exc})") from None
    rows = [(n, r) for n, r in enumerate(rows, 1) if any(c.strip() for c in r)]
    if not rows:
        raise TacestError(f"{path}: lists no object")
    header = [c.strip().lower() for c in rows[0][1]]
    unknown = [c for c in header if c not in CSV_COLUMNS]
    if unknown or "object" not in header or "run" not in header or len(set(header)) != len(header):
        raise TacestError(f"{path}: line {rows[0][0]}: the header must name the columns object and run (and "
                          f"optionally shape), got {', '.join(header) or 'nothing'}")
    out = {}
    for n, row in rows[1:]:
        if len(row) > len(header):
            raise TacestError(f"{path}: line {n}: {len(row)} fields for {len(header)} columns")
        cells = {k: (row[i].strip() if i < len(row) else "") for i, k in enumerate(header)}
        if not cells["object"] or not cells["run"]:
            raise TacestError(f"{path}: line {n}: needs an object and a run")
        runs, shape = out.setdefault(cells["object"], ([], cells.get("shape") or None))
        if (cells.get("shape") or None) != shape:
            raise TacestError(f"{path}: line {n}: object {cells['object']!r} has two shapes ({shape} and "
                              f"{cells.get('shape') or 'none'})")
        runs.append(cells["run"])
    return out


def _read_toml(path: Path) -> dict:
    """{name: ([run, ...], shape or None)} of a TOML manifest."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise TacestError(f"{path}: not a valid TOML manifest ({str(exc).splitlines()[0]})") from None
    unknown = [k for k in data if k != "objects"]
    if unknown or not isinstance(data.get("objects", {}), dict):
        raise TacestError(f"{path}: a TOML manifest holds [objects.NAME] tables only, got {', '.join(unknown)}")
    out = {}
    for name, table in data.get("objects", {}).items():
        if not isinstance(table, dict):
            raise TacestError(f"{path}: objects.{name} must be a table with runs = [...]")
        bad = [k for k in table if k not in TOML_KEYS]
        if bad:
            raise TacestError(f"{path}: objects.{name}: unknown key {bad[0]!r} (keys: {', '.join(TOML_KEYS)})")
        runs, shape = table.get("runs"), table.get("shape")
        if not isinstance(runs, list) or not all(isinstance(r, str) and r for r in runs):
            raise TacestError(f"{path}: objects.{name}.runs must be a list of run file paths")
        if shape is not None and not (isinstance(shape, str) and shape):
            raise TacestError(f"{path}: objects.{name}.shape must be a shape such as box or polygon:8")
        out[str(name)] = (list(runs), shape)
    return out


def _estimate_task(runs: list, shape: str, config, method: str) -> tuple:
    """One object's estimate where the task runs: ("ok", Estimate, s) or ("failed",
    one-line reason, s); an error no check anticipated is a reason too (a batch goes on)."""
    from tacest.dims import estimate_runs

    t0 = time.perf_counter()
    try:
        est = estimate_runs(runs, shape, config=config, method=method)
    except TacestError as exc:
        return "failed", _first_line(exc), time.perf_counter() - t0
    except Exception as exc:  # noqa: BLE001 - a bug, reported for this object only
        return "failed", f"internal error: {exc.__class__.__name__}: {_first_line(exc)}", time.perf_counter() - t0
    return "ok", est, time.perf_counter() - t0


def _first_line(exc) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else exc.__class__.__name__


def estimate_batch(objects: list, executor, shape: str = "box", config=None, method: str = "implicit") -> list:
    """Estimate every object of ``objects`` (read_manifest) on ``executor``
    (tacest.parallel.Executor); [BatchResult] in the manifest's order.  The runs are read
    and checked here; ``config`` is sent once to each worker."""
    from tacest.estimation.result import not_converged_note
    from tacest.io.run import read_runs

    results, handles = {}, {}
    loaded = {}
    for obj in objects:
        try:
            loaded[obj.name] = read_runs(obj.runs)
        except (TacestError, OSError) as exc:
            results[obj.name] = BatchResult(obj.name, obj.runs, obj.shape or shape, "failed", _first_line(exc))
    executor.plan(len(loaded), what="batch")
    cfg = executor.scatter(config)
    for obj in objects:
        if obj.name in loaded:
            handles[obj.name] = executor.submit(_estimate_task, loaded.pop(obj.name), obj.shape or shape, cfg, method,
                                                name=f"estimate-{obj.name}")
    for (name, h), (status, value, seconds) in zip(handles.items(), executor.gather(list(handles.values()))):
        obj = next(o for o in objects if o.name == name)
        results[name] = BatchResult(name, obj.runs, obj.shape or shape, status, seconds=seconds,
                                    **({"estimate": value} if status == "ok" else {"reason": value}))
        log.info(f"{name}: " + (f"{value.solver_status}, {seconds:.1f} s" if status == "ok" else f"failed: {value}"))
        note = not_converged_note(value) if status == "ok" else None
        if note:  # kept at its iteration budget (solver.solve_from_starts)
            log.warning(f"{name}: {note}")
    return [results[o.name] for o in objects]


def summary_rows(results: list) -> list:
    """One dict per object (SUMMARY_COLUMNS; None where it has no value)."""
    rows = []
    for r in results:
        row = dict.fromkeys(SUMMARY_COLUMNS)
        row.update(object=r.name, status=r.status, reason=r.reason or None, runs=len(r.runs), shape=r.shape)
        e = r.estimate
        if e is not None:
            row.update(estimate=f"{r.name}.h5", solver_status=e.solver_status, iterations=int(e.iterations),
                       wall_time=_num(e.wall_time), objective=_num(e.objective),
                       mass=_num(e.params.get("mass")), friction_ground=_num(e.params.get("friction_ground")),
                       friction_finger=_num(e.params.get("friction_finger")), fit_consistent=e.consistent)
        rows.append(row)
    return rows


def _num(v):
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def write_batch(results: list, folder, extra: Optional[dict] = None) -> list:
    """Write the batch output folder at once (module doc): NAME.h5 of every estimated
    object, summary.csv and summary.json (``extra``: more top-level keys of the JSON);
    returns the names of the files written."""
    from tacest.io.estimate import write_estimate
    from tacest.io.outputs import atomic_dir
    from tacest.provenance import provenance

    rows = summary_rows(results)
    written = []
    with atomic_dir(folder, marker=SUMMARY_JSON) as tmp:
        for r in results:
            if r.estimate is not None:
                write_estimate(r.estimate, tmp / f"{r.name}.h5")
                written.append(f"{r.name}.h5")
        with open(tmp / SUMMARY_CSV, "w", newline="", encoding="utf-8") as f:
            w = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS)
            w.writeheader()
            for row in rows:
                w.writerow({k: ("" if v is None else v) for k, v in row.items()})
        obj = {"objects": rows, "ok": sum(r.status == "ok" for r in results),
               "failed": sum(r.status != "ok" for r in results), **(extra or {}), **provenance()}
        (tmp / SUMMARY_JSON).write_text(json.dumps(obj, indent=1) + "\n", encoding="utf-8")
        written += [SUMMARY_CSV, SUMMARY_JSON]
    return written

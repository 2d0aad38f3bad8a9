"""The report folder of ``tacest diagnose -o DIR``: ``report.md`` and PNG figures.

- ``residuals_run<i>.png`` (one per run): the per-sample residual of every loss term over
  time, each in its own panel (log scale), with the finger contacts shaded, the noise
  floor drawn and the flagged windows marked;
- ``heldout_gap.png``: the held-out gap (objective above the noise floor) of the plain
  model and of every candidate, the verdict highlighted.

The folder is written through a temporary sibling and renamed into place, so a failed
report never leaves a half-written folder.  matplotlib is imported here only (Agg).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tacest.estimation.floor import TERMS
from tacest.io.outputs import atomic_dir

#: smallest value drawn on the log-scale residual panels (0.5·‖r‖² per sample)
LOG_FLOOR = 1e-4


def write_report(diag, folder, json_obj: dict = None, extra=None) -> list:
    """Write report.md, the figures and diagnosis.json into ``folder`` (created or
    replaced).  extra : ``extra(tmp) -> [file names]`` writes more files into the folder
    before it replaces ``folder`` (e.g. suggested plans), or None.  Returns the file
    names written."""
    import json

    with atomic_dir(folder) as tmp:
        names = []
        for i in range(len(diag.runs)):
            name = f"residuals_run{i}.png"
            plot_residuals(diag, i, tmp / name)
            names.append(name)
        if heldout_compared(diag):  # no figure of empty bars when no candidate could be compared
            plot_heldout(diag, tmp / "heldout_gap.png")
            names.append("heldout_gap.png")
        obj = json_obj if json_obj is not None else diag.to_json()
        (tmp / "diagnosis.json").write_text(json.dumps(obj, indent=1) + "\n")
        names.append("diagnosis.json")
        (tmp / "report.md").write_text(markdown(diag, names))
        names.insert(0, "report.md")
        if extra is not None:
            names += extra(tmp)
    return names


# ------------------------------------------------------------------------------------
# Markdown


def _f(v, fmt="{:.3g}"):
    if v is None:
        return "–"
    try:
        x = float(v)
    except (TypeError, ValueError):
        return str(v)
    if not np.isfinite(x):
        return "–"
    return fmt.format(x)


def markdown(diag, figures: list) -> str:
    """The readable summary."""
    from tacest.diagnosis.diagnose import all_screened_by_fit

    L = []
    L.append("# tacest diagnose")
    L.append("")
    files = ", ".join(f"`{r.filename or f'run {i}'}`" for i, r in enumerate(diag.runs))
    L.append(f"Runs: {files}; shape `{diag.shape}`; back end `{diag.backend}`; "
             f"{diag.wall_time:.0f} s.")
    mp = diag.mass_prior
    if mp:
        L.append("")
        L.append(f"Mass prior: {_f(mp.get('mass'))} kg, log sigma {_f(mp.get('log_sigma'))}: "
                 + ("a weighed mass, so a force-sensor gain can be told from the mass." if mp.get("known") else
                    "weak, so a force-sensor gain cannot be told from the mass (give a weighed mass with "
                    "--config to test force_scale)."))
    L.append("")
    L.append(f"## Verdict: **{diag.verdict}**")
    L.append("")
    L.append(diag.reason)
    L.append("")
    h = diag.heldout
    L.append("## Which effect, and how far (held-out data)")
    L.append("")
    L.append(f"Held-out design: {h.get('design', '–')}. The gap is the held-out objective above its noise floor "
             "(plus the plain model's Occam term where poses are observed); "
             f"a candidate counts if its improvement exceeds {_f(h.get('penalty_per_parameter'))} per added "
             "parameter, in total and, by each fold's share of that penalty, in at least half of the folds"
             + ("; one whose fit to all data improves on the plain model's by less than that is not held out "
                "(status screened)." if diag.options.fit_screen else "."))
    L.append("")
    if "gap_plain" in h:
        L.append(f"Plain model: held-out objective {_f(h.get('objective_plain'))}, floor {_f(h.get('floor'))}, "
                 f"gap {_f(h.get('gap_plain'))}; {h.get('folds_valid', 0)} of {h.get('folds', 0)} folds valid.")
        L.append("")
    L.append("| candidate | status | gap before | gap after | closed | parameters (± 1σ) | params | score | folds better |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    for c in diag.effects:
        ps = ", ".join(f"{k} = {_f(v)} ± {_f(c.params_std.get(k))}" for k, v in c.params.items()) or "–"
        mark = " **(verdict)**" if c.name == diag.verdict else ""
        closed = _f(c.reduction * 100, "{:.0f} %") if np.isfinite(c.reduction) else "–"
        L.append(f"| {c.name}{mark} | {c.status} | {_f(c.gap_before)} | {_f(c.gap_after)} | {closed} | {ps} | "
                 f"{c.n_params} | {_f(c.score)} | {c.folds_improved}/{c.folds_compared} |")
    L.append("")
    msgs = [f"- {c.name}: {c.message}" for c in diag.effects if c.message]
    if msgs:
        L += msgs + [""]
    if "heldout_gap.png" in figures:
        L.append("![held-out gap per candidate](heldout_gap.png)")
    elif all_screened_by_fit(diag.effects):
        L.append("No held-out comparison: no candidate's fit to all data improves on the plain model's by more "
                 "than its penalty, so none was held out, and there is no figure.")
    else:
        L.append("No held-out comparison: no candidate's held-out fit succeeded ("
                 + ", ".join(f"{c.name}: {c.status}" for c in diag.effects) + "), so there is no figure.")
    L.append("")
    L.append("## Where (fit of the plain model to all data)")
    L.append("")
    fm = diag.floor
    L.append(f"Windows of one contact state, at most {fm.windows} samples; {fm.mode} noise floor per degree of "
             "freedom, in contact / not (1 = the configured noise): "
             + ", ".join(f"{t} {fm.term_level(t)}" for t in TERMS) + ".")
    L.append(f"Flagged: Bonferroni-corrected chi-square tests at a family-wise false-alarm rate of "
             f"{diag.options.alpha:g}.")
    L.append("")
    if diag.where:
        L.append("| run | samples | time (s) | term | contact | excess | share | p |")
        L.append("|---|---|---|---|---|---|---|---|")
        for s in diag.where[:15]:
            t = diag.runs[s.run].time
            L.append(f"| {s.run} | {s.start}–{s.stop} | {t[s.start]:.2f}–{t[s.stop - 1]:.2f} | {s.term} | "
                     f"{'yes' if s.contact else 'no'} | {_f(s.excess)} | {_f(s.share * 100, '{:.0f} %')} | "
                     f"{_f(s.p, '{:.1e}')} |")
        if len(diag.where) > 15:
            L.append(f"| … {len(diag.where) - 15} more | | | | | | | |")
    else:
        L.append("No window stands out from the noise floor.")
    L.append("")
    L.append("Residual by term, run and contact state (largest excess first):")
    L.append("")
    L.append("| run | term | contact | ‖r‖² | expected | excess | p | flagged windows |")
    L.append("|---|---|---|---|---|---|---|---|")
    for row in diag.table[:12]:
        L.append(f"| {row['run']} | {row['term']} | {'yes' if row['contact'] else 'no'} | {_f(row['S'])} | "
                 f"{_f(row['expected'])} | {_f(row['excess'])} | {_f(row.get('p'), '{:.1e}')} | "
                 f"{row['flagged']}/{row['windows']} |")
    L.append("")
    for f in figures:
        if f.startswith("residuals_run"):
            L.append(f"![residuals]({f})")
            L.append("")
    if diag.notes:
        L.append("## Notes")
        L.append("")
        L += [f"- {n}" for n in diag.notes]
        L.append("")
    return "\n".join(L)


# ------------------------------------------------------------------------------------
# figures


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def plot_residuals(diag, i: int, path):
    """Residual per term over time for run i (see module doc)."""
    from tacest.estimation.floor import contact_state, contact_windows, residual_dof

    plt = _plt()
    run = diag.runs[i]
    res = diag.base.runs[i].residuals
    t = np.asarray(run.time, float)
    terms = [term for term in TERMS if term in res and np.any(np.asarray(res[term]) > 0)]
    if not terms:
        terms = [TERMS[0]]
    dof = residual_dof(run, np.asarray(diag.base.vertices).shape[0])
    state = contact_state(run)
    flagged = [s for s in diag.where if s.run == i]
    fig, axes = plt.subplots(len(terms), 1, figsize=(10, 1.45 * len(terms) + 1.2), sharex=True, squeeze=False)
    axes = axes[:, 0]
    for ax, term in zip(axes, terms):
        v = np.maximum(np.asarray(res.get(term, np.zeros_like(t)), float), LOG_FLOOR)
        for a, b, c in contact_windows(state, 10 ** 9):
            if c:
                ax.axvspan(t[a], t[min(b, len(t) - 1)], color="0.85", lw=0)
        for s in flagged:
            if s.term == term:
                ax.axvspan(t[s.start], t[min(s.stop, len(t) - 1)], color="tab:red", alpha=0.25, lw=0)
        ax.plot(t, v, lw=0.8, color="tab:blue")
        fl = 0.5 * diag.floor.expected_series(term, dof[term], state)
        if np.any(fl > 0):
            ax.plot(t, np.maximum(fl, LOG_FLOOR), lw=0.8, color="k", ls="--")
        ax.set_yscale("log")
        ax.set_ylabel(term, rotation=0, ha="right", va="center", fontsize=9)
        ax.tick_params(labelsize=8)
        ax.set_ylim(LOG_FLOOR * 0.8, max(float(v.max()), float(fl.max()) if fl.size else 0, 1e-2) * 3)
    axes[-1].set_xlabel("time (s)")
    name = Path(run.filename).name if run.filename else f"run {i}"
    fig.suptitle(f"{name}: residual per sample (0.5·‖r‖², whitened) — grey: finger contact, red: flagged, "
                 "dashed: noise floor", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def heldout_compared(diag) -> bool:
    """True when at least one candidate has a held-out gap to draw (its fit succeeded)."""
    return any(c.status == "ok" and np.isfinite(c.gap_after) for c in diag.effects)


def plot_heldout(diag, path):
    """Bar chart of the held-out gap per candidate (see module doc)."""
    plt = _plt()
    rows = [c for c in diag.effects]
    labels, vals, colors, notes = [], [], [], []
    gap_plain = diag.heldout.get("gap_plain")
    for c in rows:
        labels.append(c.name)
        if c.status == "ok" and np.isfinite(c.gap_after):
            vals.append(c.gap_after)
            colors.append("tab:green" if c.name == diag.verdict else ("tab:blue" if c.significant else "tab:gray"))
            notes.append(f"{c.reduction:.0%}" if np.isfinite(c.reduction) else "")
        else:
            vals.append(0.0)
            colors.append("white")
            notes.append(c.status)
    fig, ax = plt.subplots(figsize=(8, 0.42 * len(rows) + 1.6))
    y = np.arange(len(rows))[::-1]
    ax.barh(y, vals, color=colors, edgecolor="k", lw=0.5)
    title = f"held-out gap per candidate; verdict: {diag.verdict}"
    if gap_plain is not None and np.isfinite(gap_plain):
        ax.axvline(gap_plain, color="tab:red", lw=1.2)
        title += f"   (red line: the plain model's gap, {gap_plain:.3g})"
    ax.axvline(0.0, color="k", lw=0.8)
    span = max([abs(v) for v in vals] + [abs(gap_plain) if gap_plain is not None and np.isfinite(gap_plain) else 0, 1e-9])
    for yy, v, n in zip(y, vals, notes):
        ax.text(max(v, 0) + 0.01 * span, yy, n, va="center", fontsize=8)
    ax.set_yticks(y)
    ax.set_yticklabels(labels, fontsize=9)
    ax.set_xlabel("held-out gap after adding the effect (objective above the noise floor)")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

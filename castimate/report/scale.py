"""Pages and figures of the scale-out verbs: a batch's summary (``summary.html``), a Monte Carlo
study (``montecarlo.html`` and its figures) and a plan (``plan.html`` and its figure)."""

from __future__ import annotations

from datetime import datetime, timezone
from html import escape

import numpy as np
from matplotlib.figure import Figure

from ..scale.batch import BatchSummary
from ..scale.montecarlo import MonteCarloStudy
from ..scale.stats import PlanCase, crb_table, group_of, montecarlo_table, plan_table, sampling_band
from .page import CSS, fig_html, kv


def _head(title: str, what: str) -> list[str]:
    from ..version import __version__

    date = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return ["<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">",
            '<meta name="viewport" content="width=device-width, initial-scale=1">',
            f"<title>castimate {escape(what)}: {escape(title)}</title>", f"<style>{CSS}</style>\n</head>\n<body>",
            f'<h1>{escape(title)} <span class="kind">{escape(what)}</span></h1>',
            f'<p class="sub">castimate {escape(__version__)}, written {escape(date)}</p>']


def _g(x, digits: int = 4) -> str:
    if x is None or not np.isfinite(x):
        return '<span class="na">–</span>' if x is None or np.isnan(x) else "∞"
    return f"{x:.{digits}g}"


def _table(head: list[str], rows: list[list[str]], names: int = 1) -> str:
    th = "".join(f"<th>{h}</th>" for h in head)
    body = "".join("<tr>" + "".join(f'<td class="name">{c}</td>' if i < names else f"<td>{c}</td>"
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f'<div class="scroll"><table><tr>{th}</tr>{body}</table></div>'


# ---------------------------------------------------------------------------------------------
# Batch
# ---------------------------------------------------------------------------------------------

def batch_figure(summary: BatchSummary) -> Figure:
    """(x - median)/σ of every parameter (columns) and recording (rows), with the outlier threshold."""
    labels = [s.label for s in summary.spread]
    names = [n for n, r in zip(summary.names, summary.results) if r.ok]
    z = np.array([[s.z.get(n, np.nan) for s in summary.spread] for n in names]).reshape(len(names), len(labels))
    fig = Figure(figsize=(11, 3.6), layout="constrained")
    ax = fig.subplots()
    x = np.arange(len(labels))
    floor = 1e-2  # the median recording of an odd batch sits at 0: shown at the floor
    for i, n in enumerate(names):
        ax.plot(x, np.maximum(np.abs(z[i]), floor), ".", ms=4, label=n)
    ax.axhline(summary.threshold, color="#b42318", lw=1, ls="--", label=f"threshold {summary.threshold:g}")
    ax.set_yscale("log")
    ax.set_ylim(floor / 1.5, None)
    ax.set_xlabel("parameter (in the order of the table below)")
    ax.set_ylabel(f"|x − median| / σ (below {floor:g} at {floor:g})")
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=7, ncol=min(6, len(names) + 1))
    return fig


def render_batch(summary: BatchSummary) -> str:
    rows = summary.rows()
    ok = sum(r["status"] == "ok" for r in rows)
    out = _head(summary.template, "batch")
    cls = "ok" if ok == len(rows) else "warn" if ok else "bad"
    out.append(f'<p class="headline {cls}">{ok} of {len(rows)} recordings calibrated; outliers are parameters '
               f"whose |x − median| exceeds {summary.threshold:g} of that recording's σ.</p>")
    out.append("<h2>Recordings</h2>")
    diagnosed = any(r["added_effects"] is not None for r in rows)
    out.append(_table(["recording", "file", "status", "χ²/dof", "dof", "iterations", "wall [s]", "outliers"]
                      + (["effects diagnose added"] if diagnosed else []) + ["message"],
                      [[escape(r["name"]), f"<code>{escape(r['recording'])}</code>",
                        f'<span class="{"ok" if r["status"] == "ok" else "bad"}">{r["status"]}</span>',
                        _g(r["chi2_per_dof"]), _g(r["dof"]), _g(r["iterations"]), _g(r["wall_s"], 3),
                        _g(r["outliers"])] + ([escape(r["added_effects"] or "—")] if diagnosed else [])
                       + [escape(r["message"])] for r in rows], names=2))
    if summary.spread:
        out.append("<h2>Parameters over the recordings</h2>")
        out.append('<p class="note">spread: sample standard deviation over the recordings; σ: median of the σ\'s '
                   "they report (white-noise model); σ scaled: the same scaled by each recording's √(χ²/dof). A "
                   "spread/σ well above 1 means the recordings differ by more than their noise explains (other "
                   "units, a changed temperature, a missing effect).</p>")
        out.append(fig_html(batch_figure(summary), "distance from the median per parameter",
                            "Every recording's distance from the median of each parameter, in its own σ's."))
        out.append(_table(["parameter", "unit", "median", "spread", "σ", "σ scaled", "spread / σ", "outliers (z)"],
                          [[escape(s.label), escape(s.unit), _g(s.median, 6), _g(s.spread, 3), _g(s.sigma, 3),
                            _g(s.sigma_scaled, 3), _g(s.spread_over_sigma, 3),
                            escape(", ".join(f"{n} ({z:+.1f})" for n, z in s.outliers(summary.threshold).items()))]
                           for s in summary.spread]))
    out.append("</body></html>")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# Monte Carlo
# ---------------------------------------------------------------------------------------------

def montecarlo_figure(study: MonteCarloStudy) -> Figure:
    """RMSE/CRB and std(error/σ) per parameter with the 3-standard-error band, and the pooled
    error/σ against the standard normal."""
    sc = study.score
    n = len(sc.errors)
    band = sampling_band(n)
    fig = Figure(figsize=(11, 3.8), layout="constrained")
    a, b, c = fig.subplots(1, 3, width_ratios=[2, 2, 1.3])
    x = np.arange(len(sc.labels))
    for ax, y, name in ((a, sc.rmse_over_crb, "RMSE / CRB"), (b, sc.z_std, "std(error / σ)")):
        ax.axhspan(1 - band, 1 + band, color="#d8e8f5", label=f"1 ± 3/√(2N), N = {n}")
        ax.plot(x, y, ".", ms=4, color="#1f77b4")
        ax.axhline(1, color="k", lw=0.6)
        ax.set_xlabel("parameter")
        ax.set_ylabel(name)
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=7)
    z = sc.z[np.isfinite(sc.z)]
    c.hist(z, bins=41, range=(-5, 5), density=True, color="#9ecae1")
    t = np.linspace(-5, 5, 201)
    c.plot(t, np.exp(-t ** 2 / 2) / np.sqrt(2 * np.pi), color="k", lw=1, label="N(0, 1)")
    c.set_xlabel("error / σ, all parameters")
    c.legend(fontsize=7)
    return fig


def render_montecarlo(study: MonteCarloStudy, figure_file: str) -> str:
    sc, n = study.score, len(study.score.errors)
    band = sampling_band(n)
    out = _head(study.scenario, "Monte Carlo")
    r = sc.rmse_over_crb if n else np.array([np.nan])
    zs = sc.z_std if n > 1 else np.array([np.nan])
    inside = int(np.sum(np.abs(r - 1) <= band))
    cls = "ok" if n and inside == len(r) and not sc.failures else "warn"
    out.append(f'<p class="headline {cls}">{n} of {study.runs} runs solved; RMSE/CRB in [{_g(np.nanmin(r), 3)}, '
               f"{_g(np.nanmax(r), 3)}] ({inside} of {len(r)} parameters within 1 ± {band:.3f}, three standard "
               f"errors); std(error/σ) in [{_g(np.nanmin(zs), 3)}, {_g(np.nanmax(zs), 3)}].</p>")
    failures = study.failures()
    out.append(kv([("scenario", f"<code>{escape(study.scenario)}</code>"), ("runs", str(study.runs)),
                   ("failed runs", ", ".join(f"{k}: {v}" for k, v in failures.items()) or "none"),
                   ("CRB", f"{escape(study.settings.bound)}: {escape(study.bound_document()['definition'])} (the same "
                           "truth, the scenario's noise)")]))
    out.append(f'<figure><img alt="Monte Carlo scores" src="{escape(figure_file)}"><figcaption>RMSE over the CRB '
               "and the std of error/σ per parameter (1 for an efficient estimator with honest σ's), and the "
               "pooled error/σ.</figcaption></figure>")
    rows = montecarlo_table(study.score, study.bound.truth)
    out.append(_table(["parameter", "truth", "CRB", "RMSE", "RMSE / CRB", "mean error/σ", "std error/σ"],
                      [[escape(r["parameter"]), _g(r["truth"], 6), _g(r["crb"], 3), _g(r["rmse"], 3),
                        _g(r["rmse_over_crb"], 3), _g(r["mean_z"], 2), _g(r["std_z"], 3)] for r in rows]))
    bad = [r for r in study.results if not r.ok]
    if bad:
        out.append("<h2>Failed runs</h2>" + _table(["run", "reason"], [[escape(r.name), escape(r.error)] for r in bad]))
    out.append("</body></html>")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# Plan
# ---------------------------------------------------------------------------------------------

def plan_figure(cases: list[PlanCase]) -> Figure:
    """The median CRB of every parameter group (over its triads and components) against the duration."""
    labels, crb = crb_table(cases)
    units = {r["parameter"]: r["unit"] for r in plan_table(cases)}
    d = [c.duration for c in cases]
    groups = list(dict.fromkeys(group_of(lab) for lab in labels))
    fig = Figure(figsize=(7.5, 4.2), layout="constrained")
    ax = fig.subplots()
    for g in groups:
        cols = [j for j, lab in enumerate(labels) if group_of(lab) == g]
        with np.errstate(invalid="ignore"):
            y = np.array([np.median(row[cols][np.isfinite(row[cols])]) if np.isfinite(row[cols]).any() else np.nan
                          for row in crb])
        unit = units.get(labels[cols[0]], "")
        ax.loglog(d, y, "o-", ms=4, label=f"{g} [{unit or '–'}]")
    ax.set_xlabel("duration [s]")
    ax.set_ylabel("Cramér–Rao bound σ (median over the group)")
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=7)
    return fig


def render_plan(title: str, cases: list[PlanCase], figure_file: str) -> str:
    rows = plan_table(cases)
    out = _head(title, "plan")
    first = next((c for c in cases if c.undetermined), None)
    cls = "warn" if first else "ok"
    out.append(f'<p class="headline {cls}">{len(rows)} parameters; '
               + (f"undetermined directions per duration: {', '.join(f'{c.duration:g} s: {len(c.undetermined)}' for c in cases)}"
                  f" (their parameters ∞ below; the other bounds hold with those directions fixed, e.g. by a prior). At "
                  f"{first.duration:g} s: {escape('; '.join(first.undetermined))}" if first else
                  "every parameter is determined") + ".</p>")
    out.append(f'<figure><img alt="CRB against duration" src="{escape(figure_file)}"><figcaption>The bound falls '
               "with the duration as duration^a; a = −1/2 for white noise averaged longer.</figcaption></figure>")
    out.append(_table(["parameter", "unit"] + [f"{c.duration:g} s" for c in cases] + ["exponent a"],
                      [[escape(r["parameter"]), escape(r["unit"])] + [_g(r[f"crb_{c.duration:g}s"], 3) for c in cases]
                       + [_g(r["exponent"], 3)] for r in rows], names=2))
    out.append("</body></html>")
    return "\n".join(out)

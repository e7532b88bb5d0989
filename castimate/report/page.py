"""``castimate report DIR``: one self-contained ``DIR/report.html`` from ``results.json`` and
``details.npz`` (figures embedded as base64 PNG, inline CSS, no external assets).
"""

from __future__ import annotations

import base64
import io
import math
import zipfile
from datetime import datetime, timezone
from html import escape
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.readers import npz_member
from ..io.results import check_results, load_results_json
from ..output.details import DETAILS_SHAPES, check_details, check_pairing
from ..solver import verdict
from ..validation import input_file, shown

DEG = 180 / np.pi  # degrees per radian: every angle on a page is shown in degrees

CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; color: #222; margin: 0 auto;
       max-width: 1200px; padding: 1.2em 2em 3em; line-height: 1.45; }
h1 { font-size: 1.5em; margin-bottom: 0.1em; }
h1 .kind { color: #666; font-weight: normal; font-size: 0.75em; }
h2 { font-size: 1.2em; border-bottom: 1px solid #ddd; padding-bottom: 0.2em; margin-top: 1.8em; }
.sub { color: #666; margin-top: 0; font-size: 0.9em; }
.ok { color: #1a7f37; font-weight: 600; }
.warn { color: #9a6700; font-weight: 600; }
.bad { color: #b42318; font-weight: 600; }
p.headline { font-size: 1.05em; padding: 0.5em 0.8em; border-radius: 4px; border: 1px solid #d8dde3; }
p.headline.ok { background: #eaf6ec; } p.headline.warn { background: #fff6e0; } p.headline.bad { background: #fdecea; }
.scroll { max-width: 100%; }
table { border-collapse: collapse; font-size: 0.85em; margin: 0.6em 0 1em; max-width: 100%; }
table.wide { font-size: 0.7em; }
th, td { border: 1px solid #d8dde3; padding: 0.25em 0.5em; overflow-wrap: anywhere; }
th { background: #f3f5f7; font-weight: 600; text-align: center; }
td { text-align: right; font-variant-numeric: tabular-nums; }
td.name, th.name { text-align: left; font-weight: 600; }
td.na { color: #999; text-align: center; }
td.fixed { color: #777; }
tr:nth-child(even) td { background: #fafbfc; }
table.kv td { text-align: left; }
table.kv td:first-child { color: #555; }
pre.matrix { margin: 0; font-size: 0.95em; line-height: 1.2; text-align: left; }
figure { margin: 1.2em 0 2em; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { color: #444; font-size: 0.9em; margin-top: 0.3em; max-width: 60em; }
p.note { color: #555; font-size: 0.9em; margin-top: -0.4em; }
code { background: #f3f5f7; padding: 0 0.2em; border-radius: 3px; }
"""

UNIT_DISPLAY = {"-": "–", "": "–"}


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------

def load_results(directory: Path) -> dict:
    """results.json of a solved directory (structure checked; the status is reported, not enforced)."""
    path = directory / "results.json"
    input_file(path, "results file")
    doc = check_results(load_results_json(path), path, require_success=False)
    if doc.get("kind") not in DETAILS_SHAPES:
        raise InputError(path, "kind", f"expected one of {', '.join(DETAILS_SHAPES)}, found {shown(doc.get('kind'))}")
    for name, t in doc["triads"].items():
        if "parameters" not in t:
            raise InputError(path, f"triads.{name}.parameters", "missing; expected the estimated parameter groups")
    return doc


def load_details(directory: Path, required: tuple[str, ...], results: dict) -> dict[str, np.ndarray]:
    """details.npz of a solved directory, as a dict of arrays checked against results.json
    (:func:`castimate.output.details.check_details`) and paired with it (:func:`~castimate.output.details.check_pairing`)."""
    path = directory / "details.npz"
    input_file(path, "details file")
    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise InputError(path, "", f"not a readable .npz file ({e})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise InputError(path, "", "expected an .npz archive of named arrays, found a single .npy array")
    with z:
        arrays = {k: npz_member(z, k, path) for k in z.files}
    arrays = check_details(arrays, results["kind"], list(results["triads"]), path, required)
    check_pairing(arrays, results, path)
    return arrays


# ---------------------------------------------------------------------------------------------
# Formatting
# ---------------------------------------------------------------------------------------------

def finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def format_pm(value: float, std: float | None) -> str:
    """"value ± σ" with σ to two significant digits and the value to the same decimal place."""
    if not finite(value):
        return "n/a"
    if not finite(std) or std <= 0:
        return f"{value:.6g} ± ?"
    std = float(f"{std:.2g}")  # 2 significant digits first, so 9.996e-6 becomes 1.0e-5
    decimals = min(12, max(0, 1 - int(math.floor(math.log10(std)))))
    return f"{value:.{decimals}f} ± {std:.{decimals}f}"


def _unit(unit: str) -> str:
    """The display unit of a stored (SI) unit: every angle in degrees (rad -> deg, rad/s -> deg/s, ...)."""
    return UNIT_DISPLAY.get(unit, unit.replace("rad", "deg").replace("^2", "²").replace("^3", "³"))


def unit_scale(unit: str) -> float:
    """The factor from a stored (SI) unit to its display unit (:func:`_unit`)."""
    return DEG if unit.startswith("rad") else 1.0


def _sensor_of(key: str) -> tuple[str, str]:
    """results parameter key -> (sensor, group): "bias" -> accelerometer, "gyroscope.bias" -> gyroscope."""
    return tuple(key.split(".", 1)) if "." in key else ("accelerometer", key)  # type: ignore[return-value]


def parameter_tables(results: dict) -> list[tuple[str, list[str], list[str], str]]:
    """The parameter tables, one per sensor: (sensor, header HTML rows, body HTML rows, note HTML).

    One row per triad; one column per parameter component, "value ± σ" in display units (angles in
    degrees, gains as-is, biases in SI); fixed components say "fixed", absent groups "—". Groups
    fixed for every triad get no columns; the note names them.
    """
    triads = results.get("triads", {})
    reference = results.get("reference")
    order: dict[str, list[str]] = {}  # sensor -> group keys in order of appearance
    meta: dict[str, tuple[list[str], str]] = {}  # key -> (components, unit)
    for t in triads.values():
        for key, g in t.get("parameters", {}).items():
            sensor, _ = _sensor_of(key)
            if key not in meta:
                order.setdefault(sensor, []).append(key)
                meta[key] = (list(g.get("components", [])), str(g.get("unit", "")))
    tables = []
    for sensor, keys in order.items():
        fixed = [k for k in keys if not any(any(t.get("parameters", {}).get(k, {}).get("free", [False]))
                                          for t in triads.values())]
        keys = [k for k in keys if k not in fixed]
        note = ("Fixed for every triad (not estimated): "
                + ", ".join(f"{escape(_sensor_of(k)[1])}" for k in fixed) + ".") if fixed else ""
        if not keys:
            tables.append((sensor, [], [], note))
            continue
        head1 = ['<th class="name" rowspan="2">triad</th>']
        head2 = []
        for key in keys:
            comps, unit = meta[key]
            group = _sensor_of(key)[1]
            head1.append(f'<th colspan="{len(comps)}">{escape(group)} [{escape(_unit(unit))}]</th>')
            head2 += [f"<th>{escape(c)}</th>" for c in comps]
        body = []
        for name, t in triads.items():
            label = escape(name) + (" <small>(reference)</small>" if name == reference else "")
            cells = [f'<td class="name">{label}</td>']
            params = t.get("parameters", {})
            for key in keys:
                comps, unit = meta[key]
                g = params.get(key)
                if g is None:
                    cells += ['<td class="na">—</td>'] * len(comps)
                    continue
                scale = unit_scale(unit)
                for k in range(len(comps)):
                    v = g["value"][k]
                    s = g["std"][k] if g.get("std") is not None else None
                    v = v * scale if finite(v) else v
                    s = s * scale if finite(s) else s
                    if not g.get("free", [True] * len(comps))[k]:
                        cells.append(f'<td class="fixed">{v:.6g} fixed</td>' if finite(v) else
                                     '<td class="fixed">fixed</td>')
                    else:
                        cells.append(f"<td>{escape(format_pm(v, s))}</td>")
            body.append("<tr>" + "".join(cells) + "</tr>")
        tables.append((sensor, ["<tr>" + "".join(head1) + "</tr>", "<tr>" + "".join(head2) + "</tr>"], body, note))
    return tables


def wide(head: list[str]) -> str:
    """The class attribute of a table with many columns (a smaller font, so that it fits the page)."""
    return ' class="wide"' if sum(h.count("<th") for h in head[-1:]) > 12 else ""


def matrix(R: Any) -> str:
    A = np.asarray(R, float)
    if A.shape != (3, 3):
        return '<span class="na">n/a</span>'
    integer = np.allclose(A, np.round(A), atol=1e-12)
    rows = []
    for r in A:
        rows.append(" ".join(f"{int(round(x)) + 0:>2d}" if integer else f"{x:+.4f}" for x in r))
    return '<pre class="matrix">' + escape("\n".join(rows)) + "</pre>"


def fig_html(fig, alt: str, caption: str) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return (f'<figure><img alt="{escape(alt)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{caption}</figcaption></figure>")


def chi2_text(res: dict) -> str:
    """χ²/dof with dof and χ², and a hint when it lies outside the 99 % band of the noise model."""
    chi2 = res.get("chi2_per_dof")
    dof = res.get("dof")
    hint = ""
    if finite(chi2) and finite(dof) and dof > 0:
        # two-sided 99 % band of chi2/dof under the noise model (normal approximation)
        band = 2.58 * math.sqrt(2 / dof)
        if chi2 > 1 + band:
            hint = " — above 1: the residuals exceed the noise model (a missing effect or a too small σ)"
        elif chi2 < 1 - band:
            hint = " — below 1: the noise σ is larger than the residuals suggest"
    return ((f"{chi2:.3f}" if finite(chi2) else "n/a") + f" (dof {dof if dof is not None else '?'}"
            + (f", χ² {res['chi2']:.1f}" if finite(res.get("chi2")) else "") + ")" + hint)


def fit_verdict(results: dict) -> tuple[str, str]:
    """(css class, sentence) on whether the model fits the data (:func:`castimate.solver.verdict.fit_verdict`
    from results.json's solver status, χ²/dof and residual autocorrelation), as HTML."""
    status, res = results.get("status", {}), results.get("residuals", {})
    level, sentence = verdict.fit_verdict(bool(status.get("success")), str(status.get("message", "")), res.get("chi2_per_dof"),
                              res.get("dof"), (results.get("uncertainty") or {}).get("lag1_autocorrelation"))
    return level, escape(sentence).replace("castimate diagnose", "<code>castimate diagnose</code>")


def status_row(results: dict) -> tuple[str, str]:
    """The summary's solver-status row, coloured by the fit verdict (green only when it also fits)."""
    status = results.get("status", {})
    ok = bool(status.get("success"))
    cls = fit_verdict(results)[0] if ok else "bad"
    return ("solver status", f'<span class="{cls}">{"converged" if ok else "failed"}</span> '
                             f'— {escape(str(status.get("message", "")))}')


def time_base_row(results: dict) -> tuple[str, str] | None:
    """The summary's time-base row from results.json ``time_base`` (io/timestamps.py): the sampling
    rate and where it came from, whether the stamps were put on a grid, and every gap (None when
    the results carry no time base)."""
    tb = results.get("time_base")
    if not isinstance(tb, dict) or not finite(tb.get("rate_hz")):
        return None
    text = f"{tb['rate_hz']:.6g} Hz ({escape(str(tb.get('rate_from', '?')))})"
    if tb.get("repaired"):
        corr = tb.get("max_correction_s")
        text += ("; stamps put on the grid a + T n: " f"{int(tb.get('repeated_stamps') or 0)} repeated, "
                 f"{int(tb.get('backward_stamps') or 0)} backward"
                 + (f", largest correction {corr * 1e3:.3g} ms" if finite(corr) else ""))
    gaps = tb.get("gaps") or []
    if gaps:
        shown = ", ".join(f"{int(g['missing'])} before row {int(g['row'])} (t = {g['t_before_s']:.4g} s)"
                          for g in gaps[:5])
        more = f" and {len(gaps) - 5} more" if len(gaps) > 5 else ""
        text += (f'; <span class="warn">{int(tb.get("missing_samples") or 0)} samples missing in {len(gaps)} '
                 f"gap(s)</span>: {shown}{more}")
    else:
        text += "; no gaps"
    return ("time base", text)


def kv(rows: list[tuple[str, str]]) -> str:
    return '<table class="kv">' + "".join(f"<tr><td>{k}</td><td>{v}</td></tr>" for k, v in rows) + "</table>"


# ---------------------------------------------------------------------------------------------
# The report
# ---------------------------------------------------------------------------------------------

def page_head(results: dict, problem: str, kind: str, date: str | None = None) -> list[str]:
    """The opening lines of a report page, shared by every kind: head, title, provenance (castimate
    version and date) and the headline verdict on the fit."""
    from ..version import __version__

    date = date or datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    cls, verdict = fit_verdict(results)
    return [
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">",
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>castimate report: {escape(problem)}</title>",
        f"<style>{CSS}</style>\n</head>\n<body>",
        f'<h1>{escape(problem)} <span class="kind">{escape(kind)}</span></h1>',
        f'<p class="sub">castimate {escape(__version__)} calibration report, written {escape(date)}; problem '
        f'<code>{escape(str(results.get("problem", "?")))}</code>, '
        f'sha256 <code>{escape(str(results.get("problem_sha256", "?"))[:16])}…</code></p>',
        f'<p class="headline {cls}">{verdict}</p>',
    ]

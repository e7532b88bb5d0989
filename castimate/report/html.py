"""``castimate report DIR``: one self-contained ``DIR/report.html`` from ``results.json`` and
``details.npz`` (figures embedded as base64 PNG, inline CSS, no external assets).
"""

from __future__ import annotations

import base64
import io
import math
import zipfile
from html import escape
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.results import load_results_json, write_atomic
from . import figures

DEG = 180 / np.pi

REQUIRED_DETAILS = ("triads", "acc_sigma", "residual_acc", "norm_error_before", "norm_error_after")
REQUIRED_DYNAMIC_DETAILS = ("triads", "t", "omega", "omega_dot", "s", "residual_acc", "acc_sigma", "position",
                            "position_std", "nominal_position")

CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; color: #222; margin: 0 auto;
       max-width: 1200px; padding: 1.2em 2em 3em; line-height: 1.45; }
h1 { font-size: 1.5em; margin-bottom: 0.1em; }
h1 .kind { color: #666; font-weight: normal; font-size: 0.75em; }
h2 { font-size: 1.2em; border-bottom: 1px solid #ddd; padding-bottom: 0.2em; margin-top: 1.8em; }
.sub { color: #666; margin-top: 0; font-size: 0.9em; }
.ok { color: #1a7f37; font-weight: 600; }
.bad { color: #b42318; font-weight: 600; }
.scroll { overflow-x: auto; }
table { border-collapse: collapse; font-size: 0.85em; margin: 0.6em 0 1em; }
th, td { border: 1px solid #d8dde3; padding: 0.25em 0.6em; }
th { background: #f3f5f7; font-weight: 600; text-align: center; }
td { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
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

UNIT_DISPLAY = {"-": "–", "m/s^2": "m/s²", "rad": "deg", "rad/s": "rad/s", "": "–"}


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------

def load_results(directory: Path) -> dict:
    """results.json of a solved directory (format checked; the status is reported, not enforced)."""
    path = directory / "results.json"
    if not path.is_file():
        raise InputError(path, "", "not found; expected the output directory of `castimate solve PROBLEM.yaml -o DIR`")
    return load_results_json(path)


def load_details(directory: Path, required: tuple[str, ...] = REQUIRED_DETAILS) -> dict[str, np.ndarray]:
    """details.npz of a solved directory, as a dict of arrays (the *required* arrays checked)."""
    path = directory / "details.npz"
    if not path.is_file():
        raise InputError(path, "", "not found; expected the output directory of `castimate solve PROBLEM.yaml -o DIR`")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise InputError(path, "", f"not a readable .npz file ({e})") from None
    for k in required:
        if k not in arrays:
            raise InputError(path, k, "array missing; re-run `castimate solve` to regenerate details.npz")
    return arrays


# ---------------------------------------------------------------------------------------------
# Formatting
# ---------------------------------------------------------------------------------------------

def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def format_pm(value: float, std: float | None) -> str:
    """"value ± σ" with σ to two significant digits and the value to the same decimal place."""
    if not _finite(value):
        return "n/a"
    if not _finite(std) or std <= 0:
        return f"{value:.6g} ± ?"
    std = float(f"{std:.2g}")  # 2 significant digits first, so 9.996e-6 becomes 1.0e-5
    decimals = min(12, max(0, 1 - int(math.floor(math.log10(std)))))
    return f"{value:.{decimals}f} ± {std:.{decimals}f}"


def _unit(unit: str) -> str:
    return UNIT_DISPLAY.get(unit, unit.replace("^2", "²"))


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
                scale = DEG if unit == "rad" else 1.0
                for k in range(len(comps)):
                    v = g["value"][k]
                    s = g["std"][k] if g.get("std") is not None else None
                    v = v * scale if _finite(v) else v
                    s = s * scale if _finite(s) else s
                    if not g.get("free", [True] * len(comps))[k]:
                        cells.append(f'<td class="fixed">{v:.6g} fixed</td>' if _finite(v) else
                                     '<td class="fixed">fixed</td>')
                    else:
                        cells.append(f"<td>{escape(format_pm(v, s))}</td>")
            body.append("<tr>" + "".join(cells) + "</tr>")
        tables.append((sensor, ["<tr>" + "".join(head1) + "</tr>", "<tr>" + "".join(head2) + "</tr>"], body, note))
    return tables


def _matrix(R: Any) -> str:
    A = np.asarray(R, float)
    if A.shape != (3, 3):
        return '<span class="na">n/a</span>'
    integer = np.allclose(A, np.round(A), atol=1e-12)
    rows = []
    for r in A:
        rows.append(" ".join(f"{int(round(x)) + 0:>2d}" if integer else f"{x:+.4f}" for x in r))
    return '<pre class="matrix">' + escape("\n".join(rows)) + "</pre>"


def _fig_html(fig, alt: str, caption: str) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return (f'<figure><img alt="{escape(alt)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{caption}</figcaption></figure>")


def _chi2_text(res: dict) -> str:
    """χ²/dof with dof and χ², and a hint when it lies outside the 99 % band of the noise model."""
    chi2 = res.get("chi2_per_dof")
    dof = res.get("dof")
    hint = ""
    if _finite(chi2) and _finite(dof) and dof > 0:
        # two-sided 99 % band of chi2/dof under the noise model (normal approximation)
        band = 2.58 * math.sqrt(2 / dof)
        if chi2 > 1 + band:
            hint = " — above 1: the residuals exceed the noise model (a missing effect or a too small σ)"
        elif chi2 < 1 - band:
            hint = " — below 1: the noise σ is larger than the residuals suggest"
    return ((f"{chi2:.3f}" if _finite(chi2) else "n/a") + f" (dof {dof if dof is not None else '?'}"
            + (f", χ² {res['chi2']:.1f}" if _finite(res.get("chi2")) else "") + ")" + hint)


def _kv(rows: list[tuple[str, str]]) -> str:
    return '<table class="kv">' + "".join(f"<tr><td>{k}</td><td>{v}</td></tr>" for k, v in rows) + "</table>"


# ---------------------------------------------------------------------------------------------
# The report
# ---------------------------------------------------------------------------------------------

def _page_head(results: dict, problem: str, kind: str) -> list[str]:
    """The opening lines of a report page, shared by every kind: head, title and provenance."""
    return [
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">",
        f"<title>castimate report: {escape(problem)}</title>",
        f"<style>{CSS}</style>\n</head>\n<body>",
        f'<h1>{escape(problem)} <span class="kind">{escape(kind)}</span></h1>',
        f'<p class="sub">castimate calibration report; problem <code>{escape(str(results.get("problem", "?")))}</code>, '
        f'sha256 <code>{escape(str(results.get("problem_sha256", "?"))[:16])}…</code></p>',
    ]


def render_report(results: dict, details: dict[str, np.ndarray]) -> str:
    """The HTML text of a report (static or dynamic, after ``results["kind"]``)."""
    if results.get("kind") == "dynamic_array":
        return render_dynamic_report(results, details)
    problem = Path(str(results.get("problem", "?"))).name
    kind = str(results.get("kind", "?"))
    status = results.get("status", {})
    res = results.get("residuals", {})
    triads = [str(n) for n in details["triads"]]
    out: list[str] = _page_head(results, problem, kind)
    add = out.append

    # --- summary
    add("<h2>Summary</h2>")
    ok = bool(status.get("success"))
    wall, build = status.get("wall_s"), status.get("build_s")
    rows = [("solver status", f'<span class="{"ok" if ok else "bad"}">{"success" if ok else "failed"}</span> '
                              f'— {escape(str(status.get("message", "")))}'),
            ("iterations", escape(str(status.get("iterations", "?")))),
            ("solve time", f"{wall * 1e3:.0f} ms" if _finite(wall) else "n/a"),
            ("build time", f"{build * 1e3:.0f} ms" if _finite(build) else "n/a")]
    rows.append(("χ²/dof", _chi2_text(res)))
    cons = results.get("consistency")
    if cons and _finite(cons.get("ratio_db")):
        b, a = cons.get("before"), cons.get("after")
        spread = (f": spread {math.sqrt(b) * 1e3:.1f} mm/s² before → {math.sqrt(a) * 1e3:.2f} mm/s² after "
                  f"(√ of the mean over poses of the trace of the across-triad covariance)"
                  if _finite(b) and _finite(a) and b >= 0 and a >= 0 else "")
        rows.append(("array consistency (Nilsson 2014, sec. IV)", f"<b>{cons['ratio_db']:+.1f} dB</b>{spread}"))
    nb, na = details["norm_error_before"], details["norm_error_after"]
    rows.append(("gravity-norm error RMS", f"{np.sqrt(np.mean(nb ** 2)) * 1e3:.1f} mm/s² raw → "
                                           f"{np.sqrt(np.mean(na ** 2)) * 1e3:.2f} mm/s² calibrated"))
    rms = details["residual_acc"]
    rows.append(("accelerometer residual RMS", f"{np.sqrt(np.mean(rms ** 2)) * 1e3:.2f} mm/s² (all triads and axes)"))
    if "residual_gyro" in details:
        rg = details["residual_gyro"]
        rows.append(("gyroscope residual RMS", f"{np.sqrt(np.mean(rg ** 2)) * DEG * 1e3:.2f} mdeg/s "
                                               f"({len(details.get('gyro_triads', []))} triads, all axes)"))
    poses = results.get("poses", {})
    rows.append(("triads, poses", f"{len(triads)} triads (reference {escape(str(results.get('reference', '?')))}), "
                                  f"{poses.get('count', rms.shape[1])} poses"))
    if _finite(results.get("gravity")):
        rows.append(("gravity", f"{results['gravity']:.5g} m/s²"))
    add(_kv(rows))

    # --- parameters
    add("<h2>Parameters</h2>")
    add("<p>Estimates with one standard deviation from the inverse Fisher information. Angles in degrees, "
        "gains dimensionless, biases in SI units; “fixed” components were not estimated, “—” groups do not "
        "exist for that triad (the reference triad defines the array frame, so it has no misalignment).</p>")
    for sensor, head, body, note in parameter_tables(results):
        add(f"<h3>{escape(sensor.capitalize())}</h3>")
        if body:
            add('<div class="scroll"><table>' + "".join(head) + "".join(body) + "</table></div>")
        if note:
            add(f'<p class="note">{note}</p>')

    add("<h3>Nominal mounting</h3>")
    add("<p>The nominal rotation R̄ from the body frame to each triad's frame (given or recovered with "
        "<code>rotation: auto</code>), and the nominal position in the body frame.</p>")
    mrows = ['<tr><th class="name">triad</th><th>R̄ (body → triad)</th><th>position [mm]</th></tr>']
    for name, t in results.get("triads", {}).items():
        pos = t.get("position")
        pos_s = ", ".join(f"{x * 1e3:.2f}" for x in pos) if pos is not None else "—"
        mrows.append(f'<tr><td class="name">{escape(name)}</td><td>{_matrix(t.get("R_nominal"))}</td>'
                     f"<td>{escape(pos_s)}</td></tr>")
    add('<div class="scroll"><table>' + "".join(mrows) + "</table></div>")

    # --- figures
    add("<h2>Figures</h2>")
    fig = figures.residuals_per_pose(details["residual_acc"], details["acc_sigma"], triads)
    add(_fig_html(fig, "whitened residuals per pose and triad",
                  "Whitened residuals (residual / σ of the pose average) per triad and pose, and the residual "
                  "RMS per triad: with a complete model the heatmaps look like unstructured noise within about "
                  "±2; a whole row, column or axis in one colour points to an effect the model lacks in that "
                  "triad, pose or axis."))
    if "consistency_before" in details and "consistency_after" in details:
        fig = figures.consistency(details["consistency_before"], details["consistency_after"])
        add(_fig_html(fig, "array consistency per pose",
                      "Trace of the across-triad covariance of the compensated specific force per pose, with each "
                      "triad calibrated alone (before) and with the array model (after): the after bars should sit "
                      "well below the before bars in every pose, not only on average."))
    fig = figures.gravity_norm(details["norm_error_before"], details["norm_error_after"], triads)
    add(_fig_html(fig, "gravity-norm error per pose and triad",
                  "The error of the measured specific-force magnitude against g per pose and triad: calibrated "
                  "(filled) markers should be orders of magnitude below the raw (open) ones and close to the "
                  "noise level, with no triad or pose standing out."))
    fig = figures.misalignment_map(results)
    add(_fig_html(fig, "estimated misalignment and non-orthogonality angles",
                  "Misalignment and non-orthogonality angles per triad with ±1σ error bars: look for angles "
                  "that are large against the mounting tolerance, or error bars that are large against the "
                  "estimate (poorly determined angles)."))
    add("</body>\n</html>\n")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# The dynamic report (kind dynamic_array: Carlsson 2017 positions, Schopp 2016 poses)
# ---------------------------------------------------------------------------------------------

def format_mm(value: float, std: float | None) -> str:
    """A position in mm from metres: "value ± σ" with 3–4 decimals (σ to two significant digits
    where those fit); a component without σ (fixed) is the value alone with 4 decimals."""
    if not _finite(value):
        return "n/a"
    v = value * 1e3
    if not _finite(std) or std <= 0:
        return f"{v:.4f}"
    s = float(f"{std * 1e3:.2g}")
    decimals = min(4, max(3, 1 - int(math.floor(math.log10(s)))))
    return f"{v:.{decimals}f} ± {s:.{decimals}f}"


def _quaternion_group(g: dict | None) -> bool:
    return g is not None and list(g.get("components", [])) == ["w", "x", "y", "z"]


def _rotation_deg(g: dict) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vector [deg] of a misalignment quaternion group (w, x, y, z) and its σ to first
    order (2 σ of the vector part; exact for the small angles of a misalignment)."""
    q = np.asarray([np.nan if v is None else v for v in g["value"]], float)
    sq = np.asarray([np.nan if v is None else v for v in (g.get("std") or [None] * 4)], float)
    w, v = q[0], q[1:]
    n = float(np.linalg.norm(v))
    phi = 2 * v if n == 0 else 2 * math.atan2(n, w) * v / n
    return phi * DEG, 2 * sq[1:] * DEG


def _attempts_table(attempts: list) -> str:
    rows = ['<tr><th>attempt</th><th>start</th><th class="name">result</th><th>iterations</th><th>cost</th>'
            '<th class="name">local-minimum checks</th></tr>']
    for a in attempts:
        ok = bool(a.get("success"))
        issues = a.get("issues") or []
        result = (f'<span class="{"ok" if ok else "bad"}">{"converged" if ok else "failed"}</span> — '
                  f'{escape(str(a.get("message", "")))}')
        checks = ('<span class="bad">' + "; ".join(escape(str(i)) for i in issues) + "</span>" if issues
                  else '<span class="ok">passed</span>')
        cost = a.get("cost")
        rows.append(f'<tr><td>{escape(str(a.get("attempt", "?")))}</td><td class="name">'
                    f'{escape(str(a.get("start", "")))}</td><td style="text-align:left">{result}</td>'
                    f'<td>{escape(str(a.get("iterations", "?")))}</td>'
                    f'<td>{f"{cost:.6g}" if _finite(cost) else "n/a"}</td>'
                    f'<td style="text-align:left; white-space:normal">{checks}</td></tr>')
    return '<div class="scroll"><table>' + "".join(rows) + "</table></div>"


def _positions_table(results: dict, names: list[str]) -> str:
    """Per triad: nominal [mm], estimate ± σ [mm], estimate − nominal ± σ [µm] and its norm."""
    head = ['<tr><th class="name" rowspan="2">triad</th><th colspan="3">nominal [mm]</th>'
            '<th colspan="3">estimate ± σ [mm]</th><th colspan="3">estimate − nominal [µm]</th>'
            '<th rowspan="2">|Δ| [µm]</th></tr>',
            "<tr>" + "<th>x</th><th>y</th><th>z</th>" * 3 + "</tr>"]
    body = []
    reference = results.get("reference")
    for name in names:
        t = results.get("triads", {}).get(name, {})
        r = np.asarray([np.nan if v is None else v for v in t.get("position", [None] * 3)], float)
        sd = np.asarray([np.nan if v is None else v for v in t.get("position_std", [None] * 3)], float)
        nom = np.asarray([np.nan if v is None else v for v in t.get("nominal_position", [None] * 3)], float)
        free = t.get("parameters", {}).get("position", {}).get("free", [True] * 3)
        label = escape(name) + (" <small>(reference)</small>" if name == reference else "")
        cells = [f'<td class="name">{label}</td>']
        cells += [f"<td>{x * 1e3:.3f}</td>" if _finite(float(x)) else '<td class="na">n/a</td>' for x in nom]
        for k in range(3):
            if free[k]:
                cells.append(f"<td>{escape(format_mm(float(r[k]), float(sd[k])))}</td>")
            else:
                cells.append(f'<td class="fixed">{escape(format_mm(float(r[k]), None))} fixed</td>')
        d = (r - nom) * 1e6
        for k in range(3):
            if free[k]:
                cells.append(f"<td>{escape(format_pm(float(d[k]), float(sd[k] * 1e6)))}</td>")
            else:
                cells.append(f'<td class="fixed">{d[k]:.1f}</td>' if np.isfinite(d[k]) else '<td class="na">n/a</td>')
        n = float(np.linalg.norm(d))
        cells.append(f"<td>{n:.1f}</td>" if math.isfinite(n) else '<td class="na">n/a</td>')
        body.append("<tr>" + "".join(cells) + "</tr>")
    return '<div class="scroll"><table>' + "".join(head) + "".join(body) + "</table></div>"


def _orientation_table(results: dict, names: list[str]) -> tuple[str, str]:
    """(intro HTML, table HTML) of the nominal mounting R̄ and, if estimated, the misalignment."""
    triads = results.get("triads", {})
    groups = {n: triads.get(n, {}).get("parameters", {}).get("misalignment") for n in names}
    quat = any(_quaternion_group(g) and any(g.get("free", [])) for g in groups.values())
    angles = any(g is not None and not _quaternion_group(g) and any(g.get("free", [])) for g in groups.values())
    if quat:
        intro = ("<p>The misalignment of each accelerometer triad was estimated as a unit quaternion (Schopp "
                 "2016); below as its rotation vector 2·atan2(|v|, w)·v/|v| in degrees with σ = 2σ<sub>v</sub> "
                 "(first order), and the resulting orientation body → triad (misalignment times R̄) as a "
                 "quaternion. The reference triad defines the array frame.</p>")
    elif angles:
        intro = ("<p>The misalignment angles were estimated; they are in the parameter table below (degrees). "
                 "The nominal rotation R̄ (body → triad) is:</p>")
    else:
        intro = ("<p>The orientation was not estimated: each triad's axes are at the nominal rotation R̄ "
                 "(body → triad), as given or recovered with <code>rotation: auto</code>.</p>")
    head = ['<tr><th class="name" rowspan="2">triad</th><th rowspan="2">R̄ (body → triad)</th>']
    if quat:
        head[0] += ('<th colspan="3">misalignment rotation [deg]</th>'
                    '<th rowspan="2">orientation quaternion (w, x, y, z)</th></tr>')
        head.append("<tr><th>x</th><th>y</th><th>z</th></tr>")
    else:
        head[0] = head[0].replace(' rowspan="2"', "") + "</tr>"
    body = []
    for name in names:
        t = triads.get(name, {})
        label = escape(name) + (" <small>(reference)</small>" if name == results.get("reference") else "")
        cells = [f'<td class="name">{label}</td>', f"<td>{_matrix(t.get('R_nominal'))}</td>"]
        if quat:
            g = groups[name]
            if _quaternion_group(g) and any(g.get("free", [])):
                phi, sphi = _rotation_deg(g)
                cells += [f"<td>{escape(format_pm(float(a), float(b)))}</td>" for a, b in zip(phi, sphi)]
            else:
                cells += ['<td class="na">—</td>'] * 3
            q = t.get("orientation")
            cells.append("<td>" + (escape(", ".join(f"{x:+.6f}" for x in q)) if q is not None else "—") + "</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return intro, '<div class="scroll"><table>' + "".join(head) + "".join(body) + "</table></div>"


def _noise_table(results: dict, names: list[str], n_samples: int) -> str:
    """Per triad: the per-sample noise σ used and the saturated samples masked."""
    noise = results.get("noise", {}) or {}
    acc, gyro = noise.get("accelerometer") or {}, noise.get("gyroscope") or {}
    sat = results.get("saturated_samples_masked", {}) or {}
    has_gyro = bool(gyro) or any(k.endswith(".gyroscope") for k in sat)
    head = ('<tr><th class="name">triad</th><th>accelerometer σ x, y, z [mm/s²]</th>'
            + ("<th>gyroscope σ x, y, z [deg/s]</th>" if has_gyro else "")
            + "<th>accelerometer samples masked</th>" + ("<th>gyroscope samples masked</th>" if has_gyro else "")
            + "</tr>")

    def vec(v, scale):
        if v is None:
            return '<td class="na">—</td>'
        v = np.atleast_1d(np.asarray([np.nan if x is None else x for x in np.atleast_1d(v)], float)) * scale
        return "<td>" + escape(", ".join(f"{x:.3g}" for x in v)) + "</td>"

    def masked(key):
        c = sat.get(key)
        if c is None:
            return '<td class="na">—</td>'
        pct = f" ({100 * c / n_samples:.1f} %)" if c and n_samples else ""
        return (f'<td class="bad">{c}{pct}</td>' if c else f"<td>{c}</td>")

    body = []
    for name in names:
        cells = [f'<td class="name">{escape(name)}</td>', vec(acc.get(name), 1e3)]
        if has_gyro:
            cells.append(vec(gyro.get(name), DEG))
        cells.append(masked(f"{name}.accelerometer"))
        if has_gyro:
            cells.append(masked(f"{name}.gyroscope"))
        body.append("<tr>" + "".join(cells) + "</tr>")
    return '<div class="scroll"><table>' + head + "".join(body) + "</table></div>"


def _other_parameters(results: dict) -> dict:
    """results with the groups shown elsewhere (positions, quaternion misalignment) removed."""
    triads = {}
    for name, t in results.get("triads", {}).items():
        params = {k: g for k, g in t.get("parameters", {}).items()
                  if k != "position" and not (k == "misalignment" and _quaternion_group(g))}
        triads[name] = {**t, "parameters": params}
    return {**results, "triads": triads}


def render_dynamic_report(results: dict, details: dict[str, np.ndarray]) -> str:
    """The HTML text of the report of a dynamic array calibration."""
    problem = Path(str(results.get("problem", "?"))).name
    kind = str(results.get("kind", "?"))
    status = results.get("status", {})
    res = results.get("residuals", {})
    names = [str(n) for n in details["triads"]]
    t = np.asarray(details["t"], float)
    N = int(results.get("samples", len(t)) or len(t))
    out: list[str] = _page_head(results, problem, kind)
    add = out.append

    # --- summary
    add("<h2>Summary</h2>")
    ok = bool(status.get("success"))
    wall, build = status.get("wall_s"), status.get("build_s")
    attempts = status.get("attempts") or []
    rows = [("solver status", f'<span class="{"ok" if ok else "bad"}">{"success" if ok else "failed"}</span> '
                              f'— {escape(str(status.get("message", "")))}'),
            ("iterations", escape(str(status.get("iterations", "?")))),
            ("attempts", f"{len(attempts)}" + (" (restarted; see below)" if len(attempts) > 1 else "")),
            ("solve time", f"{wall * 1e3:.0f} ms" if _finite(wall) else "n/a"),
            ("build time", f"{build * 1e3:.0f} ms" if _finite(build) else "n/a"),
            ("χ²/dof", _chi2_text(res))]
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    rate = f", {(len(t) - 1) / duration:.4g} Hz" if duration > 0 else ""
    rows.append(("samples", f"{N} over {duration:.3g} s{rate}"))
    rows.append(("triads", f"{len(names)} (reference {escape(str(results.get('reference', '?')))}; "
                           f"{len(details.get('gyro_triads', []))} with a gyroscope)"))
    sat = results.get("saturated_samples_masked", {}) or {}
    masked = {k: v for k, v in sat.items() if v}
    rows.append(("saturated samples masked", "none" if not masked else
                 f'<span class="bad">{sum(masked.values())}</span> in {len(masked)} sensor(s): '
                 + ", ".join(f"{escape(k)} {v}" for k, v in masked.items())))
    m = results.get("motion_model", {}) or {}
    if m:
        def sig(key, unit):
            return f"{m[key]:.3g} {unit}" if _finite(m.get(key)) else "?"
        rows.append(("motion model", f"process model (Schopp 2016): σ_s {sig('sigma_s', 'm/s³')}, "
                                     f"σ_ω̇ {sig('sigma_omega_dot', 'rad/s³')}, "
                                     f"σ_integration {sig('sigma_integration', 'rad/s²')}"
                     if m.get("process_model") else "no process model: the motion of each sample is free"))
    ra = np.asarray(details["residual_acc"], float)
    rows.append(("accelerometer residual RMS",
                 f"{np.sqrt(np.nanmean(ra ** 2)) * 1e3:.2f} mm/s²; RMS of residual/σ "
                 f"{figures.whitened_rms(ra, details['acc_sigma']):.3f} (all triads, axes and unmasked samples)"))
    if "residual_gyro" in details and np.isfinite(details["residual_gyro"]).any():
        rg = np.asarray(details["residual_gyro"], float)
        rows.append(("gyroscope residual RMS", f"{np.sqrt(np.nanmean(rg ** 2)) * DEG * 1e3:.2f} mdeg/s "
                                               f"({len(details.get('gyro_triads', []))} triads, all axes)"))
    nom, est, sd = (np.asarray(details[k], float) for k in ("nominal_position", "position", "position_std"))
    rows.append(("positions", f"RMS distance estimated–nominal {figures.position_rms_um(nom, est, sd):.1f} µm "
                              f"over the {int(np.any(sd > 0, axis=1).sum())} estimated triad(s)"))
    add(_kv(rows))

    if attempts:
        add("<h3>Attempts</h3>")
        add("<p>Each attempt is checked for the local minima of Schopp 2016 (sec. VI-A: collapsed or "
            "diverged positions or angular motion, sign-trapped angular rates) and restarted if one is found; "
            "the converged attempt with the lowest cost is reported.</p>")
        add(_attempts_table(attempts))

    add("<h3>Noise model and masked samples</h3>")
    add("<p>The per-sample white-noise σ used to weight each triad's measurements (given in the problem or "
        "estimated from static segments), and the samples masked out of the likelihood because a sensor "
        "axis was saturated.</p>")
    add(_noise_table(results, names, N))

    # --- positions
    add("<h2>Positions</h2>")
    add("<p>Triad positions in the body frame (origin at the reference triad), estimates with one standard "
        "deviation from the inverse Fisher information; “fixed” components were not estimated.</p>")
    add(_positions_table(results, names))

    # --- orientation
    add("<h2>Orientation</h2>")
    intro, table = _orientation_table(results, names)
    add(intro)
    add(table)

    # --- other parameters
    add("<h2>Other parameters</h2>")
    add("<p>Estimates with one standard deviation. Angles in degrees, gains dimensionless, biases in SI "
        "units; “fixed” components were not estimated, “—” groups do not exist for that triad.</p>")
    tables = parameter_tables(_other_parameters(results))
    if not tables:
        add('<p class="note">No other parameters.</p>')
    for sensor, head, body, note in tables:
        add(f"<h3>{escape(sensor.capitalize())}</h3>")
        if body:
            add('<div class="scroll"><table>' + "".join(head) + "".join(body) + "</table></div>")
        if note:
            add(f'<p class="note">{note}</p>')

    # --- figures
    add("<h2>Figures</h2>")

    def fig_html(fig, caption):
        return _fig_html(fig, fig.get_suptitle(), caption)

    fig = figures.positions_on_board(names, nom, est, sd)
    f = figures.exaggeration(nom, est)
    add(fig_html(fig, "Nominal (open) and estimated (filled) positions seen from above and from the side, the "
                      + (f"errors drawn {figures._format_factor(f)} times enlarged" if f != 1 else
                         "errors drawn to scale")
                      + " with ±1σ ellipses at the same scale (often smaller than the markers): look for "
                        "triads far from the others' pattern, or errors large against the mounting tolerance."))
    fig = figures.position_errors(names, est - nom, sd)
    add(fig_html(fig, "Estimate minus nominal position per triad and axis with ±1σ error bars, and the σ's "
                      "themselves: differences many σ from zero are real deviations from the nominal layout, "
                      "not noise."))
    fig = figures.motion_over_time(t, details["omega"], details["omega_dot"], details["s"])
    add(fig_html(fig, "The estimated angular rate, angular acceleration and specific force of the body: "
                      "positions are only observable where ω and ω̇ are large, so long quiet stretches add "
                      "little information."))
    fig = figures.residuals_over_time(t, details["residual_acc"], details["acc_sigma"], names)
    add(fig_html(fig, "Whitened accelerometer residuals per triad over time (grey: masked samples) and their "
                      "RMS per triad against the noise σ: with a complete model the heatmaps look like "
                      "unstructured noise and the bars reach the σ ticks; stripes in time or a standing-out "
                      "triad point to an unmodelled effect there."))
    add("</body>\n</html>\n")
    return "\n".join(out)


def write_report(directory: Path) -> Path:
    """Write ``DIR/report.html`` for a solved directory; return its path. Raises InputError."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(directory, "", "no such directory; expected the output directory of `castimate solve`")
    results = load_results(directory)
    dynamic = results.get("kind") == "dynamic_array"
    details = load_details(directory, REQUIRED_DYNAMIC_DETAILS if dynamic else REQUIRED_DETAILS)
    path = directory / "report.html"
    write_atomic(path, render_report(results, details))
    return path

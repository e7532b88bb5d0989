"""The dynamic calibration report page.
"""

from __future__ import annotations

import math
from html import escape
from pathlib import Path

import numpy as np

from . import figures
from ..kinds.dynamic import inflation_phrase
from .page import (DEG, fig_html, chi2_text, finite, format_pm, kv, matrix, page_head, parameter_tables, status_row,
                   time_base_row, wide)
REQUIRED_DYNAMIC_DETAILS = ("triads", "t", "omega", "omega_dot", "s", "residual_acc", "acc_sigma", "position",
                            "position_std", "nominal_position")


# ---------------------------------------------------------------------------------------------
# The dynamic report (kind dynamic_array: Carlsson 2017 positions, Schopp 2016 poses)
# ---------------------------------------------------------------------------------------------

def sigma_source(results: dict) -> str:
    """Which σ's the page shows (results.json ``uncertainty.reported``), in words."""
    if (results.get("uncertainty") or {}).get("reported") == "hac":
        return ("from the HAC (Newey–West) sandwich covariance, honest under residuals correlated from sample "
                "to sample (uncertainty.residual_correlation: auto; the Fisher σ's are in results.json as "
                "std_fisher)")
    return "from the inverse Fisher information (white residuals assumed)"


def format_mm(value: float, std: float | None) -> str:
    """A position in mm from metres: "value ± σ" with 3–4 decimals (σ to two significant digits
    where those fit); a component without σ (fixed) is the value alone with 4 decimals."""
    if not finite(value):
        return "n/a"
    v = value * 1e3
    if not finite(std) or std <= 0:
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
                    f'<td>{f"{cost:.6g}" if finite(cost) else "n/a"}</td>'
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
        cells += [f"<td>{x * 1e3:.3f}</td>" if finite(float(x)) else '<td class="na">n/a</td>' for x in nom]
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
        cells = [f'<td class="name">{label}</td>', f"<td>{matrix(t.get('R_nominal'))}</td>"]
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
            + "<th>accelerometer samples masked (saturated)</th>"
            + ("<th>gyroscope samples masked (saturated)</th>" if has_gyro else "")
            + "</tr>")

    def vec(v, scale):
        if v is None:
            return '<td class="na">—</td>'
        v = np.atleast_1d(np.asarray([np.nan if x is None else x for x in np.atleast_1d(v)], float)) * scale
        return "<td>" + escape(", ".join(f"{x:.3g}" for x in v)) + "</td>"

    rails = (results.get("saturation") or {}).get("sensors") or {}

    def masked(key):
        c = sat.get(key)
        if c is None:
            return '<td class="na">—</td>'
        pct = f" ({100 * c / n_samples:.1f} %)" if c and n_samples else ""
        r = rails.get(key)
        split = (f"; low rail {r['low']}, high rail {r['high']}" + (f", {r['adjacent']} adjacent" if r["adjacent"] else "")
                 if c and r else "")
        return (f'<td class="bad">{c}{pct}{escape(split)}</td>' if c else f"<td>{c}</td>")

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


def residual_sigmas(details: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray | None, str]:
    """The σ's the report whitens the residuals with: the motion-dependent noise model's σ_n of every
    reading where it was fitted (``acc_sigma_sample`` (K, N, 3), ``gyro_sigma_sample``), else the
    static segments' σ₀ per triad and axis (K, 3); with the sentence that says which."""
    if "acc_sigma_sample" in details:
        return (np.asarray(details["acc_sigma_sample"], float),
                np.asarray(details["gyro_sigma_sample"], float) if "gyro_sigma_sample" in details else
                np.asarray(details["gyro_sigma"], float) if "gyro_sigma" in details else None,
                "residual/σ_n with the per-sample σ_n of the motion-dependent noise model")
    return (np.asarray(details["acc_sigma"], float),
            np.asarray(details["gyro_sigma"], float) if "gyro_sigma" in details else None,
            "residual/σ₀ with the static segments' σ₀ of each triad and axis (white noise)")


def render_dynamic_report(results: dict, details: dict[str, np.ndarray]) -> str:
    """The HTML text of the report of a dynamic array calibration."""
    problem = Path(str(results.get("problem", "?"))).name
    kind = str(results.get("kind", "?"))
    status = results.get("status", {})
    res = results.get("residuals", {})
    names = [str(n) for n in details["triads"]]
    t = np.asarray(details["t"], float)
    N = int(results.get("samples", len(t)) or len(t))
    out: list[str] = page_head(results, problem, kind)
    add = out.append

    # --- summary
    add("<h2>Summary</h2>")
    wall, build = status.get("wall_s"), status.get("build_s")
    attempts = status.get("attempts") or []
    rows = [status_row(results),
            ("iterations", escape(str(status.get("iterations", "?")))),
            ("attempts", f"{len(attempts)}" + (" (restarted; see below)" if len(attempts) > 1 else "")),
            ("solve time", f"{wall * 1e3:.0f} ms" if finite(wall) else "n/a"),
            ("build time", f"{build * 1e3:.0f} ms" if finite(build) else "n/a"),
            ("χ²/dof", chi2_text(res))]
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    rate = f", {(len(t) - 1) / duration:.4g} Hz" if duration > 0 else ""
    rows.append(("samples", f"{N} over {duration:.3g} s{rate}"))
    if (row := time_base_row(results)) is not None:
        rows.append(row)
    rows.append(("triads", f"{len(names)} (reference {escape(str(results.get('reference', '?')))}; "
                           f"{len(details.get('gyro_triads', []))} with a gyroscope)"))
    sat = results.get("saturated_samples_masked", {}) or {}
    masked = {k: v for k, v in sat.items() if v}
    rows.append(("saturated samples masked", "none" if not masked else
                 f'<span class="bad">{sum(masked.values())}</span> in {len(masked)} sensor(s): '
                 + ", ".join(f"{escape(k)} {v}" for k, v in masked.items())))
    m = results.get("motion_model", {}) or {}
    if m:
        levels, units = m.get("levels") or {}, m.get("units") or {}
        text = ", ".join(f"{escape(k)} {v:.4g} {escape(units.get(k, ''))}" for k, v in levels.items() if finite(v))
        est = m.get("estimate")
        rows.append(("motion model", f"process model, {escape(str(m.get('integration', '?')))} integration: {text}"
                                     + (f" (estimated from the data: variance components, {est['iterations']} "
                                        "iterations)" if est else " (given)")
                     if m.get("process_model") else "no process model: the motion of each sample is free"))
    ra = np.asarray(details["residual_acc"], float)
    acc_sigma, gyro_sigma, whitening = residual_sigmas(details)
    rows.append(("accelerometer residual RMS",
                 f"{np.sqrt(np.nanmean(ra ** 2)) * 1e3:.2f} mm/s²; RMS of residual/σ "
                 f"{figures.whitened_rms(ra, acc_sigma):.3f} (all triads, axes and unmasked samples; {whitening})"))
    if "residual_gyro" in details and np.isfinite(details["residual_gyro"]).any():
        rg = np.asarray(details["residual_gyro"], float)
        rows.append(("gyroscope residual RMS", f"{np.sqrt(np.nanmean(rg ** 2)) * DEG:.3g} deg/s "
                                               f"({len(details.get('gyro_triads', []))} triads, all axes)"
                     + (f"; RMS of residual/σ {figures.whitened_rms(rg, gyro_sigma):.3f}" if gyro_sigma is not None
                        else "")))
    u = results.get("uncertainty") or {}
    if "lag1_autocorrelation" in u:
        rho = [v for c in u["lag1_autocorrelation"].values() for v in c.values() if finite(v)]
        span = f"{min(rho):.2f}–{max(rho):.2f}" if rho else "n/a"
        rows.append(("reported σ's", f"{sigma_source(results)}; whitened residuals' lag-1 autocorrelation "
                                     f"{span} per triad and sensor, bandwidth "
                                     f"{u['bandwidth_samples']:.1f} samples, "
                                     f"{inflation_phrase(u['inflation'])} against the Fisher σ's"))
    nom, est, sd = (np.asarray(details[k], float) for k in ("nominal_position", "position", "position_std"))
    rows.append(("positions", f"RMS distance estimated–nominal {figures.position_rms_um(nom, est, sd):.1f} µm "
                              f"over the {int(np.any(sd > 0, axis=1).sum())} estimated triad(s)"))
    add(kv(rows))

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
        f"deviation {sigma_source(results)}; “fixed” components were not estimated.</p>")
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
            add(f'<div class="scroll"><table{wide(head)}>' + "".join(head) + "".join(body) + "</table></div>")
        if note:
            add(f'<p class="note">{note}</p>')

    # --- figures
    add("<h2>Figures</h2>")

    def captioned(fig, caption):
        return fig_html(fig, fig.get_suptitle(), caption)

    fig = figures.positions_on_board(names, nom, est, sd)
    f = figures.exaggeration(nom, est)
    add(captioned(fig, "Nominal (open) and estimated (filled) positions seen from above and from the side, the "
                      + (f"errors drawn {figures.format_factor(f)} times enlarged" if f != 1 else
                         "errors drawn to scale")
                      + " with ±1σ ellipses at the same scale (often smaller than the markers): look for "
                        "triads far from the others' pattern, or errors large against the mounting tolerance."))
    fig = figures.position_errors(names, est - nom, sd)
    add(captioned(fig, "Estimate minus nominal position per triad and axis with ±1σ error bars, and the σ's "
                      "themselves: differences many σ from zero are real deviations from the nominal layout, "
                      "not noise."))
    fig = figures.motion_over_time(t, details["omega"], details["omega_dot"], details["s"])
    add(captioned(fig, "The estimated angular rate, angular acceleration and specific force of the body: "
                      "positions are only observable where ω and ω̇ are large, so long quiet stretches add "
                      "little information."))
    fig = figures.residuals_over_time(t, details["residual_acc"], acc_sigma, names)
    add(captioned(fig, f"Whitened accelerometer residuals per triad over time ({whitening}; grey: masked samples) "
                      "and their RMS per triad against the noise σ: with a complete model the heatmaps look like "
                      "unstructured noise and the bars reach the σ ticks; stripes in time or a standing-out "
                      "triad point to an unmodelled effect there."))
    add("</body>\n</html>\n")
    return "\n".join(out)

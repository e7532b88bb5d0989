"""The static calibration report page.
"""

from __future__ import annotations

import math
from html import escape
from pathlib import Path

import numpy as np

from . import figures
from .page import (DEG, chi2_text, fig_html, finite, kv, matrix, page_head, parameter_tables, status_row,
                   time_base_row, wide)

REQUIRED_DETAILS = ("triads", "acc_sigma", "residual_acc", "norm_error_before", "norm_error_after")


def render_report(results: dict, details: dict[str, np.ndarray]) -> str:
    """The HTML text of a static calibration report."""
    problem = Path(str(results.get("problem", "?"))).name
    kind = str(results.get("kind", "?"))
    status = results.get("status", {})
    res = results.get("residuals", {})
    triads = [str(n) for n in details["triads"]]
    out: list[str] = page_head(results, problem, kind)
    add = out.append

    # --- summary
    add("<h2>Summary</h2>")
    wall, build = status.get("wall_s"), status.get("build_s")
    rows = [status_row(results),
            ("iterations", escape(str(status.get("iterations", "?")))),
            ("solve time", f"{wall * 1e3:.0f} ms" if finite(wall) else "n/a"),
            ("build time", f"{build * 1e3:.0f} ms" if finite(build) else "n/a")]
    rows.append(("χ²/dof", chi2_text(res)))
    cons = results.get("consistency")
    if cons and finite(cons.get("ratio_db")):
        b, a = cons.get("before"), cons.get("after")
        spread = (f": spread {math.sqrt(b) * 1e3:.1f} mm/s² before → {math.sqrt(a) * 1e3:.2f} mm/s² after "
                  f"(√ of the mean over poses of the trace of the across-triad covariance)"
                  if finite(b) and finite(a) and b >= 0 and a >= 0 else "")
        rows.append(("array consistency (Nilsson 2014, sec. IV)", f"<b>{cons['ratio_db']:+.1f} dB</b>{spread}"))
    nb, na = details["norm_error_before"], details["norm_error_after"]
    rows.append(("gravity-norm error RMS", f"{np.sqrt(np.mean(nb ** 2)) * 1e3:.1f} mm/s² raw → "
                                           f"{np.sqrt(np.mean(na ** 2)) * 1e3:.2f} mm/s² calibrated"))
    rms = details["residual_acc"]
    rows.append(("accelerometer residual RMS", f"{np.sqrt(np.mean(rms ** 2)) * 1e3:.2f} mm/s² (all triads and axes)"))
    if "residual_gyro" in details:
        rg = details["residual_gyro"]
        rows.append(("gyroscope residual RMS", f"{np.sqrt(np.mean(rg ** 2)) * DEG:.3g} deg/s "
                                               f"({len(details.get('gyro_triads', []))} triads, all axes)"))
    poses = results.get("poses", {})
    rows.append(("triads, poses", f"{len(triads)} triads (reference {escape(str(results.get('reference', '?')))}), "
                                  f"{poses.get('count', rms.shape[1])} poses"))
    if (row := time_base_row(results)) is not None:
        rows.append(row)
    if finite(results.get("gravity")):
        rows.append(("gravity", f"{results['gravity']:.5g} m/s²"))
    add(kv(rows))

    # --- parameters
    add("<h2>Parameters</h2>")
    add("<p>Estimates with one standard deviation from the inverse Fisher information. Angles in degrees, "
        "gains dimensionless, biases in SI units; “fixed” components were not estimated, “—” groups do not "
        "exist for that triad (the reference triad defines the array frame, so it has no misalignment).</p>")
    for sensor, head, body, note in parameter_tables(results):
        add(f"<h3>{escape(sensor.capitalize())}</h3>")
        if body:
            add(f'<div class="scroll"><table{wide(head)}>' + "".join(head) + "".join(body) + "</table></div>")
        if note:
            add(f'<p class="note">{note}</p>')

    add("<h3>Nominal mounting</h3>")
    add("<p>The nominal rotation R̄ from the body frame to each triad's frame (given or recovered with "
        "<code>rotation: auto</code>), and the nominal position in the body frame.</p>")
    mrows = ['<tr><th class="name">triad</th><th>R̄ (body → triad)</th><th>position [mm]</th></tr>']
    for name, t in results.get("triads", {}).items():
        pos = t.get("position")
        pos_s = ", ".join(f"{x * 1e3:.2f}" for x in pos) if pos is not None else "—"
        mrows.append(f'<tr><td class="name">{escape(name)}</td><td>{matrix(t.get("R_nominal"))}</td>'
                     f"<td>{escape(pos_s)}</td></tr>")
    add('<div class="scroll"><table>' + "".join(mrows) + "</table></div>")

    # --- figures
    add("<h2>Figures</h2>")
    fig = figures.residuals_per_pose(details["residual_acc"], details["acc_sigma"], triads)
    add(fig_html(fig, "whitened residuals per pose and triad",
                  "Whitened residuals (residual / σ of the pose average) per triad and pose, and the residual "
                  "RMS per triad: with a complete model the heatmaps look like unstructured noise within about "
                  "±2; a whole row, column or axis in one colour points to an effect the model lacks in that "
                  "triad, pose or axis."))
    if "consistency_before" in details and "consistency_after" in details:
        fig = figures.consistency(details["consistency_before"], details["consistency_after"])
        add(fig_html(fig, "array consistency per pose",
                      "Trace of the across-triad covariance of the compensated specific force per pose, with each "
                      "triad calibrated alone (before) and with the array model (after): the after bars should sit "
                      "well below the before bars in every pose, not only on average."))
    if "t_start" in details and "t_end" in details:
        fig = figures.pose_timeline(details["t_start"], details["t_end"],
                                    (results.get("detection") or {}).get("rejected", []))
        add(fig_html(fig, "static-pose detection timeline",
                      "Where the static poses were found in the recording (numbered as in the other figures) and "
                      "the candidate segments that were rejected, coloured by reason: a pose missing here, or a long "
                      "hold among the rejected ones, points to detection settings to check."))
    fig = figures.gravity_norm(details["norm_error_before"], details["norm_error_after"], triads)
    add(fig_html(fig, "gravity-norm error per pose and triad",
                  "The error of the measured specific-force magnitude against g per pose and triad: calibrated "
                  "(filled) markers should be orders of magnitude below the raw (open) ones and close to the "
                  "noise level, with no triad or pose standing out."))
    fig = figures.misalignment_map(results)
    add(fig_html(fig, "estimated misalignment and non-orthogonality angles",
                  "Misalignment and non-orthogonality angles per triad with ±1σ error bars: look for angles "
                  "that are large against the mounting tolerance, or error bars that are large against the "
                  "estimate (poorly determined angles)."))
    add("</body>\n</html>\n")
    return "\n".join(out)

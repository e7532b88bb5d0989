"""The before/after report of ``castimate diagnose``: one self-contained HTML page.

Built from the diagnosis itself (no reread of files); :mod:`castimate.io.diagnosis` supplies the
tables' numbers, :mod:`castimate.report.figures` the figure.
"""

from __future__ import annotations

from html import escape

import numpy as np

from ..kinds.diagnose import Diagnosis
from ..output.diagnosis import parameter_changes
from ..problem.clocks import sawtooth
from ..problem.effects import BY_KEY
from . import figures
from .page import DEG, fig_html, kv, page_head, format_pm


def _g(x: float, digits: int = 3) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{h}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<div class="scroll"><table><tr>{head}</tr>{body}</table></div>'


def _whitened(d: Diagnosis, outcome) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    t, per = d.session.residuals(outcome)
    return t, {sensor: np.stack([r / sig for r, sig in res.values()]) if res else np.zeros((0, 0, 3))
               for sensor, res in per.items()}


def _timing(traces) -> str:
    """Table and figure of the implied sample ages (``kinds.diagnose.TimingTrace``)."""
    fitted = np.stack([x.beat.amplitude * sawtooth(x.t, x.beat.nu, x.beat.phi) for x in traces])
    fig = figures.sample_ages([x.triad for x in traces], traces[0].t, np.stack([x.age for x in traces]),
                              np.stack([x.weight for x in traces]), np.stack([x.freqs for x in traces]),
                              np.stack([x.power for x in traces]), fitted)
    rows = [[escape(x.triad), _g(x.mean * 1e3, 3), _g(x.freqs[int(np.argmax(x.power))], 4), _g(float(np.max(x.power)), 2),
             f"{x.beat.nu:+.4f}", _g(x.beat.phi, 3), _g(x.beat.amplitude * 1e3, 3), _g(x.beat.explained, 2)]
            for x in traces]
    return (_table(["triad", "mean age [ms]", "periodogram peak [Hz]", "its variance fraction", "sawtooth ν [Hz]",
                    "φ [cycles]", "A [ms]", "variance explained"], rows)
            + fig_html(fig, "implied sample ages",
                       "Per triad, the residual along the time derivative of its readings (accelerometer and gyroscope "
                       "together), as the sample age it implies, relative to the array's mean: the motion absorbs an "
                       "age common to all triads. A chip clock beating against the read-out shows as a sawtooth and a "
                       "periodogram peak with harmonics; a clock-rate drift as a trend; a delay as an offset."))


def render_diagnosis(d: Diagnosis) -> str:
    """The HTML text of a diagnose report."""
    spec = d.spec
    b, a = d.before, d.after
    sol = a.outcome.solution  # the headline judges the final model
    head = {"problem": str(spec.path), "problem_sha256": spec.sha256,
            "status": {"success": sol.success, "message": sol.message},
            "residuals": {"chi2_per_dof": a.s2, "dof": a.dof}}
    out = page_head(head, spec.path.name, "diagnose")
    add = out.append
    added = ", ".join(f"<b>{escape(k)}</b> ({escape(BY_KEY[k].title)})" for k in d.added) or "nothing"
    add(f"<p>Effects added: {added}. Each round score-tests every library effect the model lacks at the current "
        "solution (no refit), confirms the most significant by refitting (likelihood-ratio F test at the same "
        "Bonferroni level, and the held-out prediction error must not grow), and adds it.</p>")

    def rms(res):
        return float(np.sqrt(np.nanmean(np.concatenate([r.ravel() for r in res.values()]) ** 2))) if res else np.nan

    rows = [("χ²/dof", _g(b.s2, 4), _g(a.s2, 4)),
            ("degrees of freedom", str(b.dof), str(a.dof)),
            ("residual RMS, accelerometers [mm/s²]", _g(rms(b.outcome.residual_acc) * 1e3), _g(rms(a.outcome.residual_acc) * 1e3)),
            ("residual RMS, gyroscopes [deg/s]", _g(rms(b.outcome.residual_gyro) * DEG), _g(rms(a.outcome.residual_gyro) * DEG))]
    if b.cv and a.cv:
        unit = "poses" if spec.kind == "static_array" else "blocks of samples"
        rows += [(f"held-out error, {b.cv.folds}-fold over {unit} (RMS of residual/σ)", _g(b.cv.rms, 4), _g(a.cv.rms, 4)),
                 ("held-out error, accelerometers [mm/s²]", _g(b.cv.rms_acc * 1e3), _g(a.cv.rms_acc * 1e3)),
                 ("held-out error, gyroscopes [deg/s]", _g(b.cv.rms_gyro * DEG), _g(a.cv.rms_gyro * DEG))]
    add("<h2>Before and after</h2>")
    add(_table(["", "declared model", "refined model"], [list(r) for r in rows]))
    t, wb = _whitened(d, b.outcome)
    fig = figures.diagnose_residuals(t, wb, _whitened(d, a.outcome)[1])
    add(fig_html(fig, "residuals before and after",
                  "Whitened residuals of every triad and axis over the session, declared model (left) and refined "
                  "model (right). A drift shows as a trend over time; an effect that depends on the pose or the "
                  "motion as scatter larger than 1 that does not follow time."))

    for label, traces in (("declared", d.timing_before), ("refined", d.timing_after)):
        if traces:
            add(f"<h2>Timing: the sample age the residuals imply ({label} model)</h2>")
            add(_timing(traces))

    add("<h2>Residual structure of the declared model</h2>")
    ra = d.residuals_before
    add(kv([(f"common mode ({s}): mean correlation of the triads' residuals", _g(v, 2))
             for s, v in ra.common_mode.items()]))
    add(_table(["triad", "sensor", "axis", "RMS", "χ²", "expected", "χ²/expected", "lag-1 corr. (time order)", "z"],
               [[escape(r.triad), r.sensor, r.axis, _g(r.rms), _g(r.chi2, 4), _g(r.expected, 3),
                 _g(r.chi2 / r.expected, 3), _g(r.lag1, 2), _g(r.lag1_z, 2)] for r in ra.worst(12)]))
    add('<p class="sub">The 12 triad axes with the largest χ² relative to their share of the degrees of freedom. '
        "z = lag-1 correlation × √P is about N(0, 1) for residuals that are white over time.</p>")

    for i, r in enumerate(d.rounds, 1):
        add(f"<h2>Round {i}: score tests (level α/m = {r.level:.2g})</h2>")
        add(_table(["effect", "parameters k", "LM = gᵀI⁻¹g", "F = LM/(k s²)", "p", "z", "significant"],
                   [[escape(t.effect), str(t.k), _g(t.lm, 4), _g(t.F, 4), _g(t.p, 2), _g(t.z, 3),
                     escape(t.note) if t.note else ("yes" if t.p < r.level else "no")] for t in r.tests]))
        if r.refits:
            add(_table(["refit with", "χ² before", "χ² after", "F", "p", "ΔBIC", "held-out before", "held-out after",
                        "decision"],
                       [[escape(f.effect), _g(f.chi2_before, 6), _g(f.chi2_after, 6), _g(f.F, 4), _g(f.p, 2),
                         _g(f.delta_bic, 4), _g(f.cv_before.rms if f.cv_before else np.nan, 4),
                         _g(f.cv_after.rms if f.cv_after else np.nan, 4),
                         ("<span class='ok'>added</span>: " if f.accepted else "<span class='bad'>rejected</span>: ")
                         + escape(f.reason)] for f in r.refits]))

    if d.added:
        add("<h2>Estimated effects</h2>")
        sol = a.outcome.solution
        lay = a.outcome.problem.lsq.layout
        for key in d.added:
            e = BY_KEY[key]
            rows = []
            for n in spec.array.names:
                gname = f"{n}.{e.sensor}.{e.name}"
                if gname in lay:
                    rows.append([escape(n)] + [format_pm(v, s) for v, s in zip(sol.values[gname], sol.std[gname])])
            add(f"<h3>{escape(key)}: {escape(e.title)} [{escape(e.group.unit)}]</h3>")
            add(_table(["triad"] + list(e.group.components), rows))
        reg = a.outcome.problem.config.regressors
        add(f'<p class="sub">Time regressor τ = (t − {reg.t_mid:.1f} s) / {reg.t_half:.1f} s; polynomial '
            "coefficients are the bias change at τ = ±1 (linear) and at |τ| = 1 (quadratic).</p>")

    changes = sorted(parameter_changes(d), key=lambda c: -abs(c["change_sigma"]) if np.isfinite(c["change_sigma"]) else 0)
    add("<h2>Parameter changes</h2>")
    add('<p class="sub">Parameters of the declared model, before and after, with their σ; sorted by |change|/σ '
        "(σ after). The 20 largest.</p>")
    add(_table(["parameter", "unit", "before", "after", "change / σ"],
               [[escape(f"{c['group']}[{c['component']}]"), escape(c["unit"]), format_pm(c["before"], c["std_before"]),
                 format_pm(c["after"], c["std_after"]), _g(c["change_sigma"], 3)] for c in changes[:20]]))
    add("</body>\n</html>\n")
    return "\n".join(out)

"""What ``castimate diagnose`` writes: ``diagnose.json`` and the refined problem file."""

from __future__ import annotations

import copy
import os
from pathlib import Path

import numpy as np
import yaml

from ..kinds import CrossValidation
from ..kinds.diagnose import Diagnosis, Model
from ..problem.effects import BY_KEY
from ..validation import load_yaml
from .results import dynamic_results, static_results

FORMAT = "castimate.diagnosis/1"


def _cv(cv: CrossValidation | None) -> dict | None:
    return None if cv is None else {"folds": cv.folds, "rms_whitened": cv.rms, "rms_accelerometer": cv.rms_acc,
                                    "rms_gyroscope": cv.rms_gyro, "units": {"rms_accelerometer": "m/s^2",
                                                                           "rms_gyroscope": "rad/s"},
                                    "failed_folds": list(cv.failed)}


def _times(times: dict) -> dict:
    return {k: {"wall_s": w, "cpu_s": c} for k, (w, c) in times.items()}


def _model(m: Model) -> dict:
    o = m.outcome

    def rms(res: dict) -> float:
        return float(np.sqrt(np.nanmean(np.concatenate([r.ravel() for r in res.values()]) ** 2))) if res else float("nan")

    return {"effects": list(m.effects), "chi2": m.chi2, "dof": m.dof, "chi2_per_dof": m.s2,
            "rms_accelerometer": rms(o.residual_acc), "rms_gyroscope": rms(o.residual_gyro),
            "cross_validation": _cv(m.cv), "converged": o.solution.success, "iterations": o.solution.iterations}


def parameter_changes(d: Diagnosis) -> list[dict]:
    """Every reported component present before and after: values, σ's and the change in σ's."""
    out = []
    b, a = d.before.outcome.solution, d.after.outcome.solution
    lay = d.before.outcome.problem.lsq.layout
    for g in lay.groups:
        if g.nuisance or g.name not in a.values:
            continue
        vb, va = np.atleast_1d(b.values[g.name]), np.atleast_1d(a.values[g.name])
        sb, sa = np.atleast_1d(b.std[g.name]), np.atleast_1d(a.std[g.name])
        for i, c in enumerate(g.components):
            if not g.free.ravel()[i]:
                continue
            delta = va[i] - vb[i]
            out.append({"group": g.name, "component": c, "unit": g.unit, "before": vb[i], "std_before": sb[i],
                        "after": va[i], "std_after": sa[i], "change": delta,
                        "change_sigma": delta / sa[i] if sa[i] > 0 else float("nan")})
    return out


def diagnosis_document(d: Diagnosis) -> dict:
    """The machine-readable record of a diagnosis."""
    rounds = []
    for r in d.rounds:
        rounds.append({
            "level": r.level,
            "score_tests": [{"effect": t.effect, "k": t.k, "lm": t.lm, "F": t.F, "p": t.p, "z": t.z, "note": t.note}
                            for t in r.tests],
            "refits": [{"effect": f.effect, "k": f.k, "chi2_before": f.chi2_before, "chi2_after": f.chi2_after,
                        "F": f.F, "p": f.p, "delta_bic": f.delta_bic, "accepted": f.accepted, "reason": f.reason,
                        "chi2_per_dof_after": f.model.s2 if f.model is not None else None,
                        "cv_before": _cv(f.cv_before), "cv_after": _cv(f.cv_after)} for f in r.refits],
            "times": _times(r.times),
        })

    def timing(traces):
        return {x.triad: {"mean_age_s": x.mean, "periodogram_peak_Hz": float(x.freqs[int(np.argmax(x.power))]),
                          "periodogram_peak_fraction": float(np.max(x.power)), "sawtooth": x.beat.to_dict()}
                for x in traces}

    def analysis(a):
        return {"rows": [vars(r) for r in a.rows], "common_mode": a.common_mode}

    return {"format": FORMAT, "problem": str(d.spec.path), "problem_sha256": d.spec.sha256,
            "added": d.added, "before": _model(d.before), "after": _model(d.after), "rounds": rounds,
            "residuals_before": analysis(d.residuals_before), "residuals_after": analysis(d.residuals_after),
            "timing_before": timing(d.timing_before), "timing_after": timing(d.timing_after),
            "parameter_changes": parameter_changes(d), "times": _times(d.times),
            **({"with_motion_noise": {**_model(d.final), "motion_dependent": d.final.outcome.motion_noise}}
               if d.final is not None and d.final is not d.after else {})}


def refined_problem(d: Diagnosis, out_dir: Path) -> str:
    """The problem file with the added effects declared, its paths rewritten relative to ``out_dir``
    (the original file is not touched)."""
    # as the problem was given (a file read again: 1e-3 a number, as YAML reads it)
    raw = copy.deepcopy(d.spec.source) if d.spec.source is not None else load_yaml(d.spec.path)
    base = Path(d.spec.path).resolve().parent
    rel = lambda p: os.path.relpath((base / p).resolve(), out_dir.resolve())  # noqa: E731
    data = raw["data"]
    for key in ("path", "gyro_path"):
        if isinstance(data.get(key), str):
            data[key] = rel(data[key])
    model = raw.setdefault("model", None) or {}
    raw["model"] = model
    if isinstance(model.get("intrinsics"), str):
        model["intrinsics"] = rel(model["intrinsics"])
    origin = "a problem given as a dict" if d.spec.source is not None else d.spec.path
    lines = [f"# Refined by castimate diagnose from {origin}."]
    for key in d.added:
        e = BY_KEY[key]
        section = model.setdefault(e.sensor, None) or {}
        model[e.sensor] = section
        section[e.name] = "free"
        f = next(f for r in d.rounds for f in r.refits if f.effect == key and f.accepted)
        lines.append(f"# Added {key} ({e.title}): likelihood-ratio F = {f.F:.3g}, p = {f.p:.2g}; "
                     f"held-out error {f.cv_before.rms:.4g} -> {f.cv_after.rms:.4g} (whitened RMS).")
    if not d.added:
        lines.append("# Nothing significant was found: the model is unchanged.")
    return "\n".join(lines) + "\n" + yaml.safe_dump(raw, sort_keys=False)


def final_results(d: Diagnosis) -> dict:
    """results.json of the refined model (with the declared motion-dependent noise model, if any)."""
    final = d.final or d.after
    return dynamic_results(final.outcome) if d.spec.kind == "dynamic_array" else static_results(final.outcome)

"""The results file (``results.json``, DESIGN.md contract) and atomic output.

``T`` and ``b`` are such that raw ≈ T f + b in SI units with f in the body frame, so any tool can
apply the calibration from this file alone: f = T^-1 (raw - b).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..io.readers import input_units
from ..io.results import FORMAT
from ..problem.effects import BOARD


def _units(spec, **extra) -> dict:
    """The units section: SI outputs, the data's declared units, and ``input``: the conversion the
    reader applied to the data (counts -> SI), which a device feeding raw values must apply too."""
    d = spec.data
    return {"accelerometer": "m/s^2", "gyroscope": "rad/s", **extra, "angles": "rad",
            "data_accelerometer": d.acc_units.to_dict() if d.acc_units else None,
            "data_gyroscope": d.gyro_units.to_dict() if d.gyro_units else None,
            "data_format": d.format,
            "input": {q: c.to_dict() for q, c in input_units(d.format, d.acc_units, d.gyro_units).items()}}


def _saturation(spec, sat: dict) -> dict:
    """The masking settings and, per "<triad>.<sensor>", the samples with an axis on each rail, the samples and
    the axis readings masked (each axis on its own), and where the rails came from (adc, plateau, level, none)
    with their values per axis (null where none was found)."""
    opt = spec.data.saturation
    return {"accelerometer": opt.accelerometer, "gyroscope": opt.gyroscope, "margin": opt.margin,
            "adjacent": opt.adjacent, "unit": {"accelerometer": "m/s^2", "gyroscope": "rad/s"},
            "sensors": {k: {"low": v["low"], "high": v["high"], "adjacent": v["adjacent"], "masked": v["masked"],
                            "masked_axes": v["axes"], "source": v["source"], "rail_low": v["rails"][0],
                            "rail_high": v["rails"][1]}
                        for k, v in sat.items()}}


def _parameters(layout, sol, name: str, fisher: dict | None = None) -> dict:
    """The estimated or fixed parameter groups of one triad, with σ and units (and the Fisher σ
    as ``std_fisher`` when the reported σ's are others: ``fisher`` by group)."""
    params = {}
    for g in layout.groups:
        if g.nuisance or not g.name.startswith(name + "."):
            continue
        sensor, group = (g.name.split(".")[1:] + [""])[:2]
        key = sensor if not group else group if sensor == "accelerometer" else f"{sensor}.{group}"
        params[key] = {"value": sol.values[g.name], "std": sol.std[g.name], "free": g.shaped(g.free),
                       "unit": g.unit, "components": list(g.components)}
        if fisher is not None:
            params[key]["std_fisher"] = fisher[g.name]
    return params


def static_results(outcome) -> dict:
    """The results.json document of a static calibration outcome."""
    sol, cfg, spec = outcome.solution, outcome.config, outcome.spec
    lay = outcome.problem.lsq.layout
    triads = {}
    for t in cfg.triads:
        T, b = outcome.calibration[t.name]
        entry: dict[str, Any] = {"accelerometer": {"T": T, "b": b}, "R_nominal": t.R_nominal}
        if t.name in outcome.gyro_calibration:
            Tg, bg = outcome.gyro_calibration[t.name]
            entry["gyroscope"] = {"T": Tg, "b": bg}
        if t.position is not None:
            entry["position"] = t.position
        entry["parameters"] = _parameters(lay, sol, t.name)
        triads[t.name] = entry
    rms = {n: np.sqrt((r ** 2).mean(axis=0)) for n, r in outcome.residual_acc.items()}
    doc = {
        "format": FORMAT,
        "kind": spec.kind,
        "problem": str(spec.path),
        "problem_sha256": spec.sha256,
        "status": {"success": sol.success, "message": sol.message, "iterations": sol.iterations,
                   "wall_s": sol.wall_s, "build_s": outcome.solver.build_s,
                   "elimination": outcome.solver.elimination_note},
        "gravity": cfg.gravity,
        "reference": cfg.reference,
        "units": _units(spec),
        "triads": triads,
        "residuals": {"chi2": sol.chi2, "dof": sol.dof, "chi2_per_dof": sol.chi2_per_dof, "fit": _fit(outcome),
                      "rms": rms, "rms_unit": "m/s^2",
                      "gyro_rms": {n: np.sqrt((r ** 2).mean(axis=0)) for n, r in outcome.residual_gyro.items()}},
        "poses": {"count": outcome.averages.n_poses, "samples": outcome.averages.n,
                  "t_start": outcome.averages.t_start, "t_end": outcome.averages.t_end},
    }
    det = outcome.detection
    if det is not None:
        doc["detection"] = {
            "threshold": det.threshold, "threshold_unit": "m/s^2", "gyro_threshold": det.gyro_threshold,
            "method": det.threshold_method,
            "rejected": [{"t_start": a, "t_end": b, "reason": r[2]} for (a, b), r in zip(det.rejected_times, det.rejected)],
            "notes": [{"pose": i + 1, "note": n} for i, n in det.notes],
        }
    doc.update(_effects(outcome.problem.config))
    doc["recording_notes"] = list(outcome.recording.notes)
    if outcome.recording.time_base is not None:
        doc["time_base"] = outcome.recording.time_base.as_dict()
    if outcome.consistency is not None:
        c = outcome.consistency
        doc["consistency"] = {"before": float(c.before.mean()), "after": float(c.after.mean()),
                              "ratio_db": c.ratio_db, "unit": "(m/s^2)^2",
                              "definition": "mean over poses of the trace of the across-triad covariance "
                                            "of the compensated specific force (Nilsson 2014, sec. IV)"}
    return doc


def dynamic_results(outcome) -> dict:
    """The results.json document of a dynamic calibration outcome."""
    from ..kinds.dynamic import orientation_quaternion

    sol, cfg, spec = outcome.solution, outcome.config, outcome.spec
    lay = outcome.problem.lsq.layout
    serial = outcome.serial
    fisher = serial.get("fisher_std") if serial else None
    triads = {}
    for t in cfg.triads:
        T, b = outcome.calibration[t.name]
        r, r_std = outcome.positions[t.name]
        entry = {"accelerometer": {"T": T, "b": b}, "R_nominal": t.R_nominal, "position": r, "position_std": r_std,
                 # σ scaled by sqrt(χ²/dof) when the residual exceeds the noise model: the honest
                 # figure on real data with unmodelled effects
                 "position_std_scaled": r_std * np.sqrt(max(1.0, sol.chi2_per_dof)),
                 "nominal_position": outcome.nominal[t.name], "orientation": orientation_quaternion(outcome, t.name)}
        if t.name in outcome.gyro_calibration:
            Tg, bg = outcome.gyro_calibration[t.name]
            entry["gyroscope"] = {"T": Tg, "b": bg}
        if fisher is not None:
            entry["position_std_fisher"] = fisher[f"{t.name}.position"]
        entry["parameters"] = _parameters(lay, sol, t.name, fisher)
        triads[t.name] = entry
    rms = lambda r: np.sqrt(np.nanmean(r ** 2, axis=0))  # noqa: E731
    return {
        "format": FORMAT,
        "kind": spec.kind,
        "problem": str(spec.path),
        "problem_sha256": spec.sha256,
        "status": {"success": sol.success, "message": sol.message, "iterations": sol.iterations,
                   "wall_s": sol.wall_s, "build_s": outcome.solver.build_s, "attempts": outcome.attempts,
                   "elimination": outcome.solver.elimination_note},
        "reference": cfg.reference,
        "units": _units(spec, position="m"),
        "samples": outcome.data.n,
        "saturated_samples_masked": {k: v["masked"] for k, v in outcome.saturation.items()},
        "saturation": _saturation(spec, outcome.saturation),
        "motion_model": _motion_model(cfg, outcome.variance),
        "noise": {"accelerometer": outcome.data.acc_sigma, "gyroscope": outcome.data.gyro_sigma,
                  # σ² = σ₀² + σ_d² + (τ u̇)² + (κ|ω|)² per axis (castimate.solver.motion_noise)
                  **({"motion_dependent": outcome.motion_noise} if outcome.motion_noise else {})},
        "uncertainty": _uncertainty(serial),
        "triads": triads,
        # the groups shared by every triad (problem.effects.BOARD: the chip model's sensing-element offsets)
        **({"array": {"parameters": board}} if (board := _parameters(lay, sol, BOARD, fisher)) else {}),
        "residuals": {"chi2": sol.chi2, "dof": sol.dof, "chi2_per_dof": sol.chi2_per_dof,
                      "fit": _fit(outcome),
                      "rms": {n: rms(r) for n, r in outcome.residual_acc.items()}, "rms_unit": "m/s^2",
                      "gyro_rms": {n: rms(r) for n, r in outcome.residual_gyro.items()}},
        **_effects(outcome.problem.config),
    }


def _fit(outcome) -> dict:
    """Whether the model fits the data (the outcome's ``fit``): ``level`` ok, warn or bad, and the sentence."""
    level, sentence = outcome.fit
    return {"level": level, "verdict": sentence}


def _uncertainty(serial: dict | None) -> dict:
    """Which σ's are reported ("std", "position_std"): ``hac``, the sandwich covariance under serially
    correlated residuals (castimate.solver.serial), or ``fisher``, the inverse Fisher information
    (white residuals; kept beside the others as "std_fisher", "position_std_fisher")."""
    if not serial:
        return {"reported": "fisher", "residual_correlation": "none (no time series)"}
    return {k: v for k, v in serial.items() if k not in ("fisher_std", "hac_std")}


def _motion_model(config, variance) -> dict:
    """The process model: integration, its levels (estimated or given) with their units, and the
    variance-component estimate's redundancies."""
    m = config.motion
    out = {"process_model": config.process_model, "integration": m.integration,
           "process_noise": "auto" if m.estimate else "fixed", "levels": m.levels(), "units": m.units}
    if variance is not None:
        out["estimate"] = {"iterations": variance.iterations, "converged": variance.converged,
                           "rows": variance.rows, "redundancy": variance.redundancy,
                           "not_estimable_kept": list(variance.kept),
                           "start": variance.history[0]["levels"] if variance.history else None}
    return out


def _effects(config) -> dict:
    """The included effects and how their regressors are formed, if any."""
    return {"effects": {"included": list(config.effects), "regressors": config.regressors.to_dict()}} \
        if config.effects else {}

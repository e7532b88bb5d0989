"""Short human-readable summaries of outcomes for the terminal."""

from __future__ import annotations

import numpy as np


DEG = 180 / np.pi


def _fmt(values, stds, unit) -> str:
    if unit == "rad":
        values, stds, unit = np.asarray(values) * DEG, np.asarray(stds) * DEG, "deg"
    parts = [f"{v:+.4f}±{s:.1g}" if s > 0 else f"{v:+.4f} (fixed)" for v, s in zip(values, stds)]
    return f"[{', '.join(parts)}] {unit}"


def _warning(outcome) -> list[str]:
    """The summary's line saying that the model does not fit (the outcome's ``fit``), if it does not."""
    level, sentence = outcome.fit
    return [f"  warning: {sentence}"] if level == "bad" else []


def static_summary(outcome) -> str:
    sol = outcome.solution
    lay = outcome.problem.lsq.layout
    lines = [f"{outcome.spec.path.name}: {sol.message} in {sol.iterations} iterations, "
             f"{sol.wall_s * 1e3:.0f} ms solve + {outcome.solver.build_s * 1e3:.0f} ms build",
             f"  {outcome.averages.n_poses} poses, {len(outcome.config.triads)} triads, "
             f"chi2/dof = {sol.chi2_per_dof:.3f} (dof {sol.dof})", *_warning(outcome)]
    for name in outcome.config.names:
        r = outcome.residual_acc[name]
        lines.append(f"  {name}: residual RMS {np.sqrt((r ** 2).mean()) * 1e3:.2f} mm/s^2")
        for g in lay.groups:
            if g.name.startswith(name + ".") and g.free.any():
                lines.append(f"    {g.name.split('.', 1)[1]:32s} {_fmt(sol.values[g.name], sol.std[g.name], g.unit)}")
    ge = outcome.gravity_norm_error
    before = np.sqrt(np.mean([np.mean(b ** 2) for b, _ in ge.values()]))
    after = np.sqrt(np.mean([np.mean(a ** 2) for _, a in ge.values()]))
    lines.append(f"  gravity-norm error RMS: {before * 1e3:.1f} mm/s^2 raw -> {after * 1e3:.2f} mm/s^2 calibrated")
    time_base = outcome.recording.time_base
    lines += [f"  {note}" for note in (time_base.alerts if time_base is not None else ())]
    if outcome.consistency is not None:
        c = outcome.consistency
        lines.append(f"  array consistency (Nilsson sec. IV): {np.sqrt(c.before.mean()) * 1e3:.1f} -> "
                     f"{np.sqrt(c.after.mean()) * 1e3:.1f} mm/s^2, {c.ratio_db:+.1f} dB")
    return "\n".join(lines)


def dynamic_summary(outcome) -> str:
    sol = outcome.solution
    lines = [f"{outcome.spec.path.name}: {sol.message} in {sol.iterations} iterations "
             f"({len(outcome.attempts)} attempt(s)), {sol.wall_s:.2f} s solve + {outcome.solver.build_s:.2f} s build",
             f"  {outcome.data.n} samples, {len(outcome.config.triads)} triads, chi2/dof = {sol.chi2_per_dof:.3f}",
             f"  solver: {outcome.solver.elimination_note}"]
    m = outcome.config.motion
    if outcome.config.process_model:
        lines.append(f"  process model: {m.integration}, levels "
                     + ", ".join(f"{k} {v:.4g} {m.units[k]}" for k, v in m.levels().items())
                     + (f" (estimated, {outcome.variance.iterations} iterations"
                        + (f"; not estimable, kept as given: {', '.join(outcome.variance.kept)}" if outcome.variance.kept
                           else "") + ")" if outcome.variance is not None else " (given)"))
    masked = {k: v for k, v in outcome.saturation.items() if v["masked"]}
    if masked:
        lines.append("  saturated samples masked (on the low rail / the high rail; axis readings): " + ", ".join(
            f"{k} {v['masked']} ({v['low']} / {v['high']}" + (f", {v['adjacent']} adjacent" if v["adjacent"] else "")
            + f"; {v['axes']})" for k, v in masked.items()))
    for sensor, comps in (outcome.motion_noise or {}).items():
        if isinstance(comps, dict) and any(c["value"] for c in comps.values()):
            lines.append(f"  motion-dependent noise, {sensor}: " + ", ".join(
                f"{k} {c['value']:.3g}±{c['std']:.2g} {c['unit']}" for k, c in comps.items() if c["value"]))
    if (outcome.motion_noise or {}).get("status"):
        lines.append(f"  motion-dependent noise: {outcome.motion_noise['status']}")
    lines += _warning(outcome)
    lines.append("  position [mm] (body frame, origin at the reference triad)  estimate ± σ   | nominal")
    for n in outcome.config.names:
        r, s = outcome.positions[n]
        nom = outcome.nominal[n]
        est = ", ".join(f"{a * 1e3:+8.3f}±{b * 1e3:.3f}" if b > 0 else f"{a * 1e3:+8.3f} (fixed)" for a, b in zip(r, s))
        lines.append(f"    {n:8s} [{est}] | [{', '.join(f'{x * 1e3:+.3f}' for x in nom)}]")
    for g in outcome.problem.lsq.layout.groups:
        if not g.nuisance and "position" not in g.name and g.free.any():
            lines.append(f"    {g.name:32s} {_fmt(sol.values[g.name], sol.std[g.name], g.unit)}")
    return "\n".join(lines)

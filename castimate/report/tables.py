"""Markdown tables across results: parameter spread over sessions (Nilsson 2014, Table I) and a
comparison of a raw-count calibration with manufacturer values."""

from __future__ import annotations

import numpy as np

from ..models.effects import along_sensing_axes, chip_to_body
from ..problem.compensation import linear_inverse

DEG = 180 / np.pi
# (parameter key, component, column title, factor to display units)
TABLE_I_COLUMNS = [("gain", i, f"k_{a} [-]", 1.0) for i, a in enumerate("xyz")] + \
    [("bias", i, f"b_{a} [m/s²]", 1.0) for i, a in enumerate("xyz")] + \
    [("nonorthogonality", i, f"l_{c} [°]", DEG) for i, c in enumerate(("yx", "zx", "zy"))] + \
    [("misalignment", i, f"ξ_{a} [°]", DEG) for i, a in enumerate("xyz")]


def _fmt(x: float) -> str:
    return f"{x:.4f}" if abs(x) < 10 else f"{x:.1f}"


def session_spread(results: list[dict], sessions: list[str]) -> str:
    """Mean (range) of every accelerometer parameter over sessions, one row per triad."""
    triads = list(results[0]["triads"])
    head = "| triad | " + " | ".join(c[2] for c in TABLE_I_COLUMNS) + " |"
    lines = [f"Mean (range) over {len(results)} sessions ({', '.join(sessions)}).", "", head,
             "|" + "---|" * (len(TABLE_I_COLUMNS) + 1)]
    for t in triads:
        cells = []
        for key, i, _, f in TABLE_I_COLUMNS:
            p = results[0]["triads"][t]["parameters"].get(key)
            if p is None or not p["free"][i]:
                cells.append("–")
                continue
            v = np.array([r["triads"][t]["parameters"][key]["value"][i] for r in results]) * f
            cells.append(f"{_fmt(v.mean())} ({v.max() - v.min():.1e})")
        lines.append(f"| {t} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def session_summary(results: list[dict], sessions: list[str]) -> str:
    """Per session: convergence, χ²/dof, residual RMS, consistency before/after in dB."""
    lines = ["| session | status | iterations | χ²/dof | residual RMS [mm/s²] | consistency before → after [mm/s²] | ratio [dB] |",
             "|---|---|---|---|---|---|---|"]
    for s, r in zip(sessions, results):
        rms = np.sqrt(np.mean([np.mean(np.square(v)) for v in r["residuals"]["rms"].values()])) * 1e3
        c = r.get("consistency", {})
        cons = f"{np.sqrt(c['before']) * 1e3:.1f} → {np.sqrt(c['after']) * 1e3:.1f}" if c else "–"
        db = f"{c['ratio_db']:+.1f}" if c else "–"
        lines.append(f"| {s} | {r['status']['message']} | {r['status']['iterations']} | "
                     f"{r['residuals']['chi2_per_dof']:.2f} | {rms:.2f} | {cons} | {db} |")
    return "\n".join(lines)


def counts_comparison(result: dict, triad: str, sensor: str, nominal_offset, nominal_scale) -> str:
    """Offsets [counts] and scales [counts per SI unit] implied by a calibration of raw counts,
    against nominal values. The problem's unit declaration (counts -> SI) is undone first."""
    units = result["units"][f"data_{sensor}"]
    s0, o0 = np.asarray(units["scale"], float), np.asarray(units["offset"], float)
    cal = result["triads"][triad][sensor]
    T, b = np.asarray(cal["T"]), np.asarray(cal["b"])
    offset = o0 + b / s0
    scale = np.diag(T) / s0
    si = "m/s²" if sensor == "accelerometer" else "rad/s"
    lines = [f"| {sensor} axis | offset castimate [counts] | offset nominal | scale castimate [counts/({si})] | scale nominal |",
             "|---|---|---|---|---|"]
    for i, a in enumerate("xyz"):
        ns = "–" if nominal_scale is None else f"{nominal_scale[i]:.0f}"
        lines.append(f"| {a} | {offset[i]:.1f} | {nominal_offset[i]:.0f} | {scale[i]:.1f} | {ns} |")
    return "\n".join(lines)


def gravity_norm_rms(acc_si: np.ndarray, T: np.ndarray, b: np.ndarray, g: float) -> float:
    """RMS over poses of | |T^-1 (y - b)| - g |, m/s²."""
    f = linear_inverse(T, b, acc_si)
    return float(np.sqrt(np.mean((np.linalg.norm(f, axis=1) - g) ** 2)))


def sensing_axis_positions(res: dict) -> dict[str, np.ndarray]:
    """Per triad of a results document, its position coordinate by coordinate from the accelerometer
    sensing element that measures it (:func:`castimate.models.effects.along_sensing_axes`): with
    ``accelerometer.axis_offsets`` free, ``position`` is the x element's; ``accelerometer.chip_axis_offsets`` (the
    array's, in the chip frame) gives each triad's through its nominal rotation. Without offsets: ``position``."""
    out = {}
    chip = res.get("array", {}).get("parameters", {}).get("chip_axis_offsets", {}).get("value")
    for n, t in res["triads"].items():
        delta = t.get("parameters", {}).get("axis_offsets", {}).get("value")
        if chip is not None:
            delta = chip_to_body(t["R_nominal"], chip)
        out[n] = np.asarray(t["position"], float) if delta is None else \
            along_sensing_axes(t["position"], delta, t["R_nominal"])
    return out


def in_plane_ratio(res: dict, sensing_axes: bool = False) -> float:
    """Σ of the estimated in-plane (x, y) distances between triads over Σ of the nominal ones, over the pairs
    apart in x or y: the array's scale (1 when the geometry's scale is right). ``sensing_axes``: each
    coordinate from the sensing element along it (:func:`sensing_axis_positions`), not the x element's."""
    names = list(res["triads"])
    pos = sensing_axis_positions(res) if sensing_axes else {n: np.asarray(res["triads"][n]["position"]) for n in names}
    nom = {n: np.asarray(res["triads"][n]["nominal_position"]) for n in names}
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:] if np.linalg.norm(nom[a][:2] - nom[b][:2]) > 1e-3]
    return float(sum(np.linalg.norm(pos[a][:2] - pos[b][:2]) for a, b in pairs)
                 / sum(np.linalg.norm(nom[a][:2] - nom[b][:2]) for a, b in pairs))


def dynamic_summary_table(results: list[dict], sessions: list[str]) -> str:
    """Per session of a dynamic calibration: samples, gyro samples on each rail, attempts, χ²/dof, residual RMS,
    the in-plane distance ratio to the nominal layout."""
    lines = ["| session | samples | gyro samples masked (summed over gyroscopes; on the low / high rail) | attempts | "
             "iterations | χ²/dof | accelerometer residual RMS [m/s²] | in-plane distance ratio to nominal |",
             "|---|---|---|---|---|---|---|---|"]
    for s, r in zip(sessions, results):
        masked = sum(v for k, v in r["saturated_samples_masked"].items() if k.endswith("gyroscope"))
        rails = [v for k, v in (r.get("saturation") or {}).get("sensors", {}).items() if k.endswith("gyroscope")]
        split = f" ({sum(v['low'] for v in rails)} / {sum(v['high'] for v in rails)})" if rails else ""
        rms = np.sqrt(np.mean([np.mean(np.square(v)) for v in r["residuals"]["rms"].values()]))
        lines.append(f"| {s} | {r['samples']} | {masked}{split} | {len(r['status']['attempts'])} | {r['status']['iterations']} | "
                     f"{r['residuals']['chi2_per_dof']:.0f} | {rms:.3f} | {in_plane_ratio(r):.4f} |")
    return "\n".join(lines)


def position_spread(results: list[dict], sessions: list[str]) -> str:
    """Estimated positions per triad: nominal, mean over sessions, range, σ (white-noise and scaled)."""
    lines = [f"Positions in mm, body frame (origin at the reference triad); mean and range (max - min) over "
             f"{', '.join(sessions)}; σ is the median over sessions, white-noise model / scaled by √(χ²/dof).", "",
             "| triad | nominal x, y, z | mean x, y, z | range x, y, z [µm] | σ [µm] | σ scaled [µm] |", "|---|---|---|---|---|---|"]
    for t in results[0]["triads"]:
        nom = np.asarray(results[0]["triads"][t]["nominal_position"]) * 1e3
        est = np.array([r["triads"][t]["position"] for r in results]) * 1e3
        sd = np.median([np.mean(r["triads"][t]["position_std"]) for r in results]) * 1e6
        sds = np.median([np.mean(r["triads"][t]["position_std_scaled"]) for r in results]) * 1e6
        f3 = lambda v: ", ".join(f"{x:+.3f}" for x in v)  # noqa: E731
        lines.append(f"| {t} | {f3(nom)} | {f3(est.mean(axis=0))} | "
                     f"{', '.join(f'{x:.0f}' for x in (est.max(axis=0) - est.min(axis=0)) * 1e3)} | {sd:.1f} | {sds:.0f} |")
    return "\n".join(lines)


def session_position_spread(results: list[dict], std: str = "position_std") -> tuple[float, float]:
    """(RMS over triads and components of the positions' standard deviation across sessions, RMS of the
    reported σ's) [m], the reference triad (fixed at the origin) left out: σ's are honest when the two agree.
    ``std``: which σ's (``position_std_fisher``: the Fisher σ's beside reported HAC ones)."""
    names = [n for n in results[0]["triads"] if np.any(results[0]["triads"][n]["position_std"])]
    est = np.array([[r["triads"][n]["position"] for n in names] for r in results])
    sd = np.array([[r["triads"][n][std] for n in names] for r in results])
    return float(np.sqrt(np.mean(np.var(est, axis=0, ddof=1)))), float(np.sqrt(np.mean(sd ** 2)))

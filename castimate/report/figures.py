"""Report figures: pure functions from numpy arrays (SI units in, display units on the axes) to
matplotlib Figures. No IO here; :mod:`castimate.report.html` renders and embeds them.
"""

from __future__ import annotations

from typing import Sequence

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

DEG = 180 / np.pi
AXES = ("x", "y", "z")
AXIS_COLORS = ("#1f77b4", "#2ca02c", "#d62728")  # x, y, z
BEFORE_COLOR = "#9e9e9e"
AFTER_COLOR = "#1f77b4"


def _new_figure(width: float, height: float) -> Figure:
    # Figure() rather than plt.figure(): nothing is registered with pyplot, so nothing leaks.
    return Figure(figsize=(width, height), layout="constrained")


def _triad_ticks(ax, names: Sequence[str], axis: str = "x", rotate: bool | None = None) -> None:
    names = list(names)
    rotate = len(names) > 8 or max((len(n) for n in names), default=0) > 6 if rotate is None else rotate
    if axis == "x":
        ax.set_xticks(np.arange(len(names)))
        ax.set_xticklabels(names, rotation=45 if rotate else 0, ha="right" if rotate else "center",
                           rotation_mode="anchor" if rotate else "default")
    else:
        ax.set_yticks(np.arange(len(names)))
        ax.set_yticklabels(names)


def _pose_ticks(ax, n_poses: int, axis: str = "x") -> None:
    """Pose numbers (1-based), every pose up to 25, else a readable subset."""
    step = 1 if n_poses <= 25 else int(np.ceil(n_poses / 20))
    idx = np.arange(0, n_poses, step)
    setter = (ax.set_xticks, ax.set_xticklabels) if axis == "x" else (ax.set_yticks, ax.set_yticklabels)
    setter[0](idx)
    setter[1]([str(i + 1) for i in idx], fontsize=8 if n_poses > 12 else None)


def _positive_floor(*arrays: np.ndarray) -> float:
    """A floor for log axes: a decade below the smallest positive value (1e-12 if there is none)."""
    pos = np.concatenate([np.ravel(a)[np.ravel(a) > 0] for a in arrays]) if arrays else np.array([])
    pos = pos[np.isfinite(pos)]
    return float(pos.min() / 10) if pos.size else 1e-12


def residuals_per_pose(residual: np.ndarray, sigma: np.ndarray, triads: Sequence[str]) -> Figure:
    """Whitened accelerometer residuals and per-triad residual RMS.

    Parameters
    ----------
    residual
        (M, P, 3) residual y − (T f + b) of the pose-averaged readings, m/s².
    sigma
        (M, P, 3) standard deviation of those averages, m/s² (the whitening σ).
    triads
        The M triad names.

    Returns a figure with three heatmaps (triads × poses; one per sensor axis) of residual/σ on a
    diverging colour scale symmetric around 0, and below them the residual RMS per triad and axis in
    mm/s² as grouped bars.
    """
    residual = np.asarray(residual, float)
    sigma = np.asarray(sigma, float)
    M, P, _ = residual.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(sigma > 0, residual / sigma, np.nan)
    finite = np.abs(w[np.isfinite(w)])
    # Symmetric scale; a few outliers should not wash out the rest, so clip at the 99.5 % quantile
    # (the colour bar then shows an arrow) but never below ±3 σ, so a good fit looks pale.
    vmax = max(3.0, float(np.quantile(finite, 0.995))) if finite.size else 3.0
    clipped = finite.size and finite.max() > vmax

    heat_h = max(2.2, 0.22 * M + 1.0)
    fig = _new_figure(max(9.0, min(16.0, 3 * (0.18 * P + 1.2) + 1.5)), heat_h + 3.2)
    gs = fig.add_gridspec(2, 3, height_ratios=[heat_h, 3.0])
    axes = [fig.add_subplot(gs[0, 0])]
    axes += [fig.add_subplot(gs[0, k], sharey=axes[0]) for k in (1, 2)]
    im = None
    for k, ax in enumerate(axes):
        im = ax.imshow(w[:, :, k], cmap="RdBu_r", vmin=-vmax, vmax=vmax, aspect="auto", interpolation="nearest")
        ax.set_title(f"{AXES[k]} axis")
        ax.set_xlabel("pose")
        _pose_ticks(ax, P)
        if k == 0:
            _triad_ticks(ax, triads, axis="y")
            ax.set_ylabel("triad")
        else:
            ax.tick_params(labelleft=False)
    cb = fig.colorbar(im, ax=axes, extend="both" if clipped else "neither", fraction=0.04, pad=0.01)
    cb.set_label("residual / σ")

    ax = fig.add_subplot(gs[1, :])
    rms = np.sqrt(np.nanmean(residual ** 2, axis=1)) * 1e3  # (M, 3) mm/s^2
    x = np.arange(M)
    width = 0.8 / 3
    for k in range(3):
        ax.bar(x + (k - 1) * width, rms[:, k], width, color=AXIS_COLORS[k], label=f"{AXES[k]} axis")
    _triad_ticks(ax, triads)
    pad = max(0.6, (4 - M) / 2 + 0.1)  # keep the bars narrow for one or two triads
    ax.set_xlim(-pad, M - 1 + pad)
    ax.set_ylabel("residual RMS [mm/s²]")
    ax.set_title("Residual RMS over the poses, per triad and axis")
    ax.legend(ncols=3, fontsize=8, loc="upper left", frameon=False)
    ax.set_ylim(0, rms.max() * 1.2 if np.isfinite(rms).any() and rms.max() > 0 else 1)
    ax.grid(axis="y", alpha=0.3)
    fig.suptitle("Accelerometer residuals of the array model")
    return fig


def consistency(before: np.ndarray, after: np.ndarray) -> Figure:
    """Array consistency per pose (Nilsson, Skog, Händel 2014, sec. IV).

    Parameters
    ----------
    before, after
        (P,) trace of the across-triad sample covariance of the compensated specific force,
        (m/s²)²; *before* with each triad calibrated alone (gain, bias, non-orthogonality, no
        misalignment), *after* with the full array model.

    Bars per pose on a log axis; the title gives 10·log10(mean(after)/mean(before)) in dB.
    """
    before = np.asarray(before, float)
    after = np.asarray(after, float)
    P = before.shape[0]
    ratio_db = 10 * np.log10(after.mean() / before.mean())
    fig = _new_figure(max(7.0, min(14.0, 0.35 * P + 3)), 4.0)
    ax = fig.add_subplot()
    x = np.arange(P)
    floor = _positive_floor(before, after)
    ax.bar(x - 0.2, np.maximum(before, floor), 0.4, color=BEFORE_COLOR,
           label="before: each triad alone, no misalignment")
    ax.bar(x + 0.2, np.maximum(after, floor), 0.4, color=AFTER_COLOR, label="after: array model")
    ax.axhline(before.mean(), color=BEFORE_COLOR, ls="--", lw=1)
    ax.axhline(after.mean(), color=AFTER_COLOR, ls="--", lw=1)
    ax.set_yscale("log")
    ax.set_xlim(-0.6, P - 0.4)
    _pose_ticks(ax, P)
    ax.set_xlabel("pose")
    ax.set_ylabel("tr cov across triads [(m/s²)²]")
    ax.grid(axis="y", which="major", alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    handles.append(Line2D([], [], color="k", ls="--", lw=1))
    labels.append("mean over poses")
    ax.legend(handles, labels, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncols=3,
              frameon=False)
    ax.set_title(f"Array consistency per pose: mean ratio after/before = {ratio_db:+.1f} dB")
    return fig


def gravity_norm(before: np.ndarray, after: np.ndarray, triads: Sequence[str]) -> Figure:
    """| |f| − g | per pose and triad, before (raw readings) and after calibration.

    Parameters
    ----------
    before, after
        (M, P) absolute gravity-norm error, m/s².
    triads
        The M triad names.

    One marker per pose and triad (colour = triad, open = raw, filled = calibrated), spread
    sideways by triad within each pose, on a log axis in mm/s².
    """
    before = np.asarray(before, float) * 1e3
    after = np.asarray(after, float) * 1e3
    M, P = before.shape
    floor = _positive_floor(before, after)
    cmap = plt.get_cmap("tab10" if M <= 10 else "tab20")
    colors = [cmap(i % cmap.N) for i in range(M)]
    offsets = (np.arange(M) - (M - 1) / 2) * (0.7 / max(M, 1))
    fig = _new_figure(max(8.0, min(15.0, 0.4 * P + 4)), 4.6)
    ax = fig.add_subplot()
    x = np.arange(P)
    for i in range(M):
        ax.plot(x + offsets[i], np.maximum(before[i], floor), "o", mfc="none", mec=colors[i], ms=4.5, mew=1)
        ax.plot(x + offsets[i], np.maximum(after[i], floor), "o", color=colors[i], ms=4)
    for p in range(P - 1):
        ax.axvline(p + 0.5, color="0.9", lw=0.8, zorder=0)
    ax.set_yscale("log")
    ax.set_xlim(-0.6, P - 0.4)
    _pose_ticks(ax, P)
    ax.set_xlabel("pose (markers within a pose: one per triad)")
    ax.set_ylabel("| |f| − g |  [mm/s²]")
    rb = np.sqrt(np.mean(before ** 2))
    ra = np.sqrt(np.mean(after ** 2))
    ax.set_title(f"Gravity-norm error: RMS {rb:.3g} mm/s² raw → {ra:.3g} mm/s² calibrated")
    ax.grid(axis="y", which="major", alpha=0.3)
    handles = [Line2D([], [], ls="", marker="o", mfc="none", mec="k", ms=5),
               Line2D([], [], ls="", marker="o", color="k", ms=5),
               Line2D([], [], ls="", marker="")]
    handles += [Line2D([], [], ls="", marker="s", color=colors[i], ms=6) for i in range(M)]
    labels = ["raw", "calibrated", ""] + list(triads)
    ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False,
              ncols=1 if M <= 16 else 2)
    return fig


# Parameter groups shown by misalignment_map, in order: (results key, panel title).
ANGLE_GROUPS = (("misalignment", "Accelerometer misalignment ξ to the reference triad"),
                ("nonorthogonality", "Accelerometer non-orthogonality (L below the diagonal)"),
                ("gyroscope.misalignment", "Gyroscope misalignment"),
                ("gyroscope.nonorthogonality", "Gyroscope non-orthogonality"))


def misalignment_map(results: dict) -> Figure:
    """Estimated angles per triad with ±σ error bars, grouped by triad, in degrees.

    One panel per angle group present with at least one free component in ``results["triads"]``
    (misalignment, non-orthogonality, and their gyroscope counterparts). Each triad gets a
    group of three markers (one per component); a triad without that group, such as the reference
    triad for misalignment, is labelled in its slot, and fixed components are drawn hollow.
    """
    triads = results.get("triads", {})
    names = list(triads)
    reference = results.get("reference")
    panels = []
    for key, title in ANGLE_GROUPS:
        groups = {n: triads[n].get("parameters", {}).get(key) for n in names}
        if any(g is not None and any(g.get("free", [])) for g in groups.values()):
            panels.append((key, title, groups))
    M = len(names)
    fig = _new_figure(max(8.0, min(16.0, 0.6 * M + 3)), 0.6 + 2.9 * max(len(panels), 1))
    if not panels:
        ax = fig.add_subplot()
        ax.text(0.5, 0.5, "no misalignment or non-orthogonality was estimated", ha="center", va="center",
                transform=ax.transAxes)
        ax.set_axis_off()
        return fig
    axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    x = np.arange(M)
    for ax, (key, title, groups) in zip(axes, panels):
        comps = next(g["components"] for g in groups.values() if g is not None)
        nc = len(comps)
        offs = (np.arange(nc) - (nc - 1) / 2) * 0.22
        for k in range(nc):
            color = AXIS_COLORS[k % 3]
            for i, n in enumerate(names):
                g = groups[n]
                if g is None:
                    continue
                v = float(g["value"][k]) * DEG
                s = g["std"][k]
                s = float(s) * DEG if s is not None and np.isfinite(s) else 0.0
                free = bool(g["free"][k])
                ax.errorbar(x[i] + offs[k], v, yerr=s if free else None, fmt="o", color=color, ms=4.5,
                            mfc=color if free else "none", capsize=2.5, elinewidth=1.2)
            ax.plot([], [], "o", color=color, label=comps[k])
        for i, n in enumerate(names):
            if groups[n] is None:
                ax.text(x[i], 0.5, "reference" if n == reference else "not estimated", rotation=90,
                        ha="center", va="center", fontsize=8, color="0.45", transform=ax.get_xaxis_transform())
        for i in range(M - 1):
            ax.axvline(i + 0.5, color="0.9", lw=0.8, zorder=0)
        ax.axhline(0, color="0.6", lw=0.8, zorder=0)
        stds = [float(s) * DEG for g in groups.values() if g is not None
                for s, f in zip(g["std"], g["free"]) if f and s is not None and np.isfinite(s)]
        if stds:
            title += f"  (median σ = {np.median(stds):.2g}°)"
        ax.set_ylabel("angle [deg]")
        ax.set_title(title, fontsize=10)
        ax.legend(title="component", title_fontsize=8, fontsize=8, loc="upper left",
                  bbox_to_anchor=(1.005, 1.0), frameon=False)
        ax.grid(axis="y", alpha=0.3)
        ax.set_xlim(-0.6, M - 0.4)
    _triad_ticks(axes[-1], names)
    axes[-1].set_xlabel("triad")
    any_fixed = any(g is not None and not all(g["free"]) for _, _, gs in panels for g in gs.values())
    fig.suptitle("Estimated angles (±1σ error bars" + ("; hollow = fixed)" if any_fixed else ")"))
    return fig

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


def pose_timeline(t_start: np.ndarray, t_end: np.ndarray, rejected: Sequence[dict]) -> Figure:
    """The static-pose detection over the recording: accepted poses (numbered, as in the other
    figures) and rejected candidate segments with their reason.

    Parameters
    ----------
    t_start, t_end
        (P,) time range of each accepted pose, s.
    rejected
        ``results.json`` ``detection.rejected`` entries: ``t_start``, ``t_end`` (s) and ``reason``.
    """
    t_start, t_end = np.asarray(t_start, float), np.asarray(t_end, float)
    fig = _new_figure(12.0, 2.4)
    ax = fig.add_subplot()
    ax.broken_barh([(a, b - a) for a, b in zip(t_start, t_end)], (0.55, 0.4), color=AFTER_COLOR)
    for i, (a, b) in enumerate(zip(t_start, t_end)):
        if len(t_start) <= 60 or i % 5 == 0:
            ax.text((a + b) / 2, 1.0, str(i + 1), ha="center", va="bottom", fontsize=7)
    reasons = sorted({str(r.get("reason", "")) for r in rejected})
    colors = _category_colors(len(reasons))
    for reason, c in zip(reasons, colors):
        spans = [(r["t_start"], r["t_end"] - r["t_start"]) for r in rejected if str(r.get("reason", "")) == reason]
        ax.broken_barh(spans, (0.05, 0.4), color=c, label=f"rejected: {reason[:60]}")
    ax.set_yticks([0.25, 0.75], ["rejected", "poses"])
    ax.set_ylim(0, 1.35)
    ends = [x for x in (t_end.max() if t_end.size else None,
                        max((r["t_end"] for r in rejected), default=None)) if x is not None]
    starts = [x for x in (t_start.min() if t_start.size else None,
                          min((r["t_start"] for r in rejected), default=None)) if x is not None]
    if starts and ends:
        ax.set_xlim(min(starts), max(ends))
    ax.set_xlabel("time [s]")
    ax.set_title(f"Static-pose detection: {len(t_start)} poses accepted, {len(rejected)} segments rejected")
    if reasons:
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.35), ncols=2, frameon=False)
    return fig


def _category_colors(n: int) -> list:
    """n distinct colours for categories (matplotlib's tab10 cycle)."""
    from matplotlib import colormaps

    return [colormaps["tab10"](i % 10) for i in range(n)]


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


# ---------------------------------------------------------------------------------------------
# Dynamic array (Carlsson 2017 positions, Schopp 2016 poses)
# ---------------------------------------------------------------------------------------------

def _nice_factor(x: float) -> float:
    """The 1-2-5 number nearest to *x* on a log scale (1 for a non-finite or non-positive x)."""
    if not np.isfinite(x) or x <= 0:
        return 1.0
    e = np.floor(np.log10(x))
    cands = np.array([1, 2, 5, 10]) * 10.0 ** e
    return float(cands[np.argmin(np.abs(np.log(cands / x)))])


def format_factor(f: float) -> str:
    return f"{f:.0f}" if f >= 1 else f"{f:.3g}"


def triad_spacing(nominal: np.ndarray) -> float:
    """Typical triad spacing, m: the median distance to the nearest triad at a different x–y
    position (triads stacked on the two sides of a board share x–y), else in 3-D; 0 if undefined."""
    p = np.asarray(nominal, float)
    if len(p) < 2:
        return 0.0
    for cols in ((0, 1), (0, 1, 2)):
        d = np.linalg.norm(p[:, None, cols] - p[None, :, cols], axis=-1)
        tol = 1e-3 * max(float(d.max()), 1e-12)
        d[d <= tol] = np.inf
        nn = d.min(axis=1)
        nn = nn[np.isfinite(nn)]
        if nn.size:
            return float(np.median(nn))
    return 0.0


def exaggeration(nominal: np.ndarray, estimated: np.ndarray) -> float:
    """A 1-2-5 factor that draws the largest position error at about a third of the triad spacing
    (at least 1: errors already that large are drawn true to scale)."""
    err = np.linalg.norm(np.asarray(estimated, float) - np.asarray(nominal, float), axis=1)
    err = err[np.isfinite(err)]
    spacing = triad_spacing(nominal)
    if not err.size or err.max() <= 0 or spacing <= 0:
        return 1.0
    return max(1.0, _nice_factor(spacing / 3 / err.max()))  # never shrink the errors


def position_rms_um(nominal: np.ndarray, estimated: np.ndarray, std: np.ndarray) -> float:
    """RMS distance estimated–nominal in µm over the estimated triads (those with a σ > 0; a triad
    fixed at its nominal position, such as the reference, would only dilute it)."""
    d = np.linalg.norm(np.asarray(estimated, float) - np.asarray(nominal, float), axis=1)
    est = np.any(np.asarray(std, float) > 0, axis=1)
    d = d[est & np.isfinite(d)] if est.any() else d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d ** 2)) * 1e6) if d.size else float("nan")


def positions_title(nominal: np.ndarray, estimated: np.ndarray, std: np.ndarray) -> str:
    n = int(np.any(np.asarray(std, float) > 0, axis=1).sum())
    return (f"Triad positions: RMS distance estimated–nominal {position_rms_um(nominal, estimated, std):.1f} µm"
            f" ({n} estimated triad{'' if n == 1 else 's'})")


def _levels(z: np.ndarray, tol: float) -> np.ndarray:
    """Index of the z level (board side) of each triad: sorted z values split at gaps > tol."""
    order = np.argsort(z)
    lev = np.zeros(len(z), int)
    k = 0
    for a, b in zip(order[:-1], order[1:]):
        if z[b] - z[a] > tol:
            k += 1
        lev[b] = k
    return lev.max() - lev  # 0 = the highest level (top side)


def positions_on_board(names: Sequence[str], nominal: np.ndarray, estimated: np.ndarray, std: np.ndarray) -> Figure:
    """Nominal and estimated triad positions, from above (x–y) and from the side (x–z).

    Parameters
    ----------
    names
        The K triad names.
    nominal, estimated, std
        (K, 3) nominal position, estimate and its σ in the body frame, m.

    Nominal positions are open markers, estimates filled markers at nominal + f·(estimate −
    nominal) with the factor f chosen so the largest error is about a third of the triad spacing
    (stated in the legend); the ±1σ ellipses are drawn at the same factor. Colour = board side
    (z level). The title gives the RMS distance estimated–nominal in µm.
    """
    from matplotlib.patches import Ellipse

    names = list(names)
    nom = np.asarray(nominal, float) * 1e3  # mm
    est = np.asarray(estimated, float) * 1e3
    sd = np.asarray(std, float) * 1e3
    K = len(names)
    f = exaggeration(nominal, estimated)
    shown = nom + f * (est - nom)
    spacing = triad_spacing(nominal) * 1e3
    lev = _levels(nom[:, 2], max(0.5, 0.05 * spacing)) if K else np.zeros(0, int)
    n_lev = int(lev.max()) + 1 if K else 1
    side_colors = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd"]
    colors = [side_colors[v] if n_lev <= len(side_colors) else "#1f77b4" for v in lev]

    # limits in mm: nominal, shown estimates and ellipses, with a margin for the labels
    pts = np.concatenate([nom, shown + f * sd, shown - f * sd]) if K else np.zeros((1, 3))
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = max(float((hi - lo)[:2].max()), spacing, 1e-3)
    margin = 0.06 * span + 0.2 * spacing
    lo, hi = lo - margin, hi + margin
    # both views at the same scale (equal aspect): panel heights follow the data extents, the side
    # view padded in z to a readable minimum height
    width = 9.5
    plot_w = width - 1.3
    scale = plot_w / (hi[0] - lo[0])  # inch per mm
    if (hi[1] - lo[1]) * scale > 8.5:  # a tall board: limit the height, narrower panels
        scale = 8.5 / (hi[1] - lo[1])
    zmin_span = 1.5 / scale
    if hi[2] - lo[2] < zmin_span:
        mid = (hi[2] + lo[2]) / 2
        lo[2], hi[2] = mid - zmin_span / 2, mid + zmin_span / 2
    top_h, side_h = (hi[1] - lo[1]) * scale, (hi[2] - lo[2]) * scale
    fig = _new_figure(width, top_h + side_h + 2.0)
    gs = fig.add_gridspec(2, 1, height_ratios=[top_h, side_h])
    ax_top = fig.add_subplot(gs[0])
    ax_side = fig.add_subplot(gs[1], sharex=ax_top)

    for ax, (a, b) in ((ax_top, (0, 1)), (ax_side, (0, 2))):
        for i in range(K):
            c = colors[i]
            ax.plot([nom[i, a], shown[i, a]], [nom[i, b], shown[i, b]], "-", color=c, lw=1.0, alpha=0.8)
            if np.isfinite(sd[i, [a, b]]).all() and (sd[i, [a, b]] > 0).any():
                ax.add_patch(Ellipse((shown[i, a], shown[i, b]), 2 * f * sd[i, a], 2 * f * sd[i, b],
                                     fill=False, ec=c, lw=0.9, ls="--"))
            ax.plot(nom[i, a], nom[i, b], "o", mfc="white", mec=c, ms=6.5, mew=1.2)
            ax.plot(shown[i, a], shown[i, b], "o", color=c, ms=4)
        ax.set_aspect("equal", adjustable="box")
        ax.grid(alpha=0.25)
    ax_top.set_xlim(lo[0], hi[0])
    ax_top.set_ylim(lo[1], hi[1])
    ax_side.set_ylim(lo[2], hi[2])
    # names beside the nominal markers (below the markers, so these stay visible); triads on the
    # two sides of a board share an x–y position, so the sides get opposite corners
    fs = 8 if K <= 16 else 7
    for i, n in enumerate(names):
        up = lev[i] % 2 == 0
        ax_top.annotate(n, (nom[i, 0], nom[i, 1]), xytext=(-5, 4 if up else -4), textcoords="offset points",
                        ha="right", va="bottom" if up else "top", fontsize=fs, color=colors[i], zorder=1.5,
                        bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.75))
    ax_top.set_ylabel("y [mm]")
    ax_top.set_title("Top view (x–y)", fontsize=10)
    ax_top.tick_params(labelbottom=False)
    ax_side.set_xlabel("x [mm]")
    ax_side.set_ylabel("z [mm]")
    ax_side.set_title("Side view (x–z)", fontsize=10)

    fs_ = format_factor(f)
    handles = [Line2D([], [], ls="", marker="o", mfc="white", mec="k", ms=6.5, mew=1.2),
               Line2D([], [], ls="-", marker="o", color="k", ms=4, lw=1.0),
               Line2D([], [], ls="--", color="k", lw=0.9)]
    labels = ["nominal", f"estimate, error ×{fs_}" + (" (true scale)" if f == 1 else ""), f"±1σ ellipse, ×{fs_}"]
    if 1 < n_lev <= len(side_colors):
        for v in range(n_lev):
            z = np.median(nom[lev == v, 2])
            handles.append(Line2D([], [], ls="", marker="s", color=side_colors[v], ms=7))
            labels.append(f"nominal z ≈ {z:.1f} mm")
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 5), fontsize=8, frameon=False)
    fig.suptitle(positions_title(nominal, estimated, std))
    return fig


def position_errors(names: Sequence[str], diff: np.ndarray, std: np.ndarray) -> Figure:
    """Estimated minus nominal position per triad and axis with ±1σ error bars, µm.

    Parameters
    ----------
    names
        The K triad names.
    diff, std
        (K, 3) estimate − nominal and the σ of the estimate, m.

    Top: the differences (one marker per axis, grouped by triad); triads whose position was not
    estimated (σ = 0, such as the reference) are labelled instead. Bottom: the σ's as bars, since
    they are often far smaller than the differences and their error bars then vanish.
    """
    names = list(names)
    d = np.asarray(diff, float) * 1e6
    s = np.asarray(std, float) * 1e6
    K = len(names)
    fixed = ~np.any(s > 0, axis=1)
    x = np.arange(K)
    offs = (np.arange(3) - 1) * 0.22
    fig = _new_figure(max(8.0, min(16.0, 0.42 * K + 3)), 6.2)
    ax, ax_s = fig.subplots(2, 1, sharex=True, height_ratios=[3.2, 1.6])
    for k in range(3):
        sel = ~fixed
        ax.errorbar(x[sel] + offs[k], d[sel, k], yerr=s[sel, k], fmt="o", color=AXIS_COLORS[k], ms=4,
                    capsize=2.5, elinewidth=1.2, label=AXES[k])
        ax_s.bar(x[sel] + offs[k], s[sel, k], 0.22, color=AXIS_COLORS[k])
    for i in np.flatnonzero(fixed):
        for a in (ax, ax_s):
            a.text(x[i], 0.5, "fixed", rotation=90, ha="center", va="center", fontsize=8, color="0.45",
                   transform=a.get_xaxis_transform())
    for a in (ax, ax_s):
        for i in range(K - 1):
            a.axvline(i + 0.5, color="0.9", lw=0.8, zorder=0)
        a.grid(axis="y", alpha=0.3)
        a.set_xlim(-0.6, K - 0.4)
    ax.axhline(0, color="0.6", lw=0.8, zorder=0)
    ax.set_ylabel("estimate − nominal [µm]")
    ax.legend(title="axis", title_fontsize=8, fontsize=8, loc="upper left", bbox_to_anchor=(1.005, 1.0),
              frameon=False)
    ax.set_title("Difference to the nominal position (±1σ error bars)", fontsize=10)
    top = np.nanmax(s[~fixed]) if (~fixed).any() else 0.0
    ax_s.set_ylim(0, top * 1.15 if np.isfinite(top) and top > 0 else 1)
    ax_s.set_ylabel("σ [µm]")
    ax_s.set_title("Standard deviation of the estimate", fontsize=10)
    _triad_ticks(ax_s, names)
    ax_s.set_xlabel("triad")
    fig.suptitle(f"Position errors: RMS |estimate − nominal| "
                 f"{position_rms_um(np.zeros_like(d), np.asarray(diff, float), std):.1f} µm")
    return fig


def motion_over_time(t: np.ndarray, omega: np.ndarray, omega_dot: np.ndarray, s: np.ndarray) -> Figure:
    """The estimated body motion: ω [deg/s], ω̇ [deg/s²] and the specific force s at the body
    origin [m/s²], stacked over a shared time axis in s. Inputs in SI units: t (N,), the rest (N, 3)."""
    t = np.asarray(t, float)
    series = ((np.asarray(omega, float) * DEG, "angular rate ω [deg/s]"),
              (np.asarray(omega_dot, float) * DEG, "angular acceleration ω̇ [deg/s²]"),
              (np.asarray(s, float), "specific force s [m/s²]"))
    fig = _new_figure(11.0, 7.5)
    axes = fig.subplots(3, 1, sharex=True)
    lw = 1.0 if len(t) <= 2000 else 0.6
    for ax, (y, label) in zip(axes, series):
        for k in range(3):
            ax.plot(t, y[:, k], color=AXIS_COLORS[k], lw=lw, label=AXES[k])
        ax.set_ylabel(label, fontsize=9)
        ax.grid(alpha=0.3)
        ax.axhline(0, color="0.6", lw=0.6, zorder=0)
    axes[0].legend(ncols=3, fontsize=8, loc="upper right", bbox_to_anchor=(1.0, 1.22), frameon=False)
    if len(t):
        axes[-1].set_xlim(t[0], t[-1])
    axes[-1].set_xlabel("time [s]")
    fig.suptitle("Estimated motion of the body frame (specific force at the reference triad)")
    return fig


def _per_sample(sigma: np.ndarray) -> np.ndarray:
    """σ (K, 3) per triad and axis or (K, N, 3) per sample, as (K, 1 or N, 3) against residuals (K, N, 3)."""
    sg = np.asarray(sigma, float)
    return sg[:, None, :] if sg.ndim == 2 else sg


def whitened_rms(residual: np.ndarray, sigma: np.ndarray) -> float:
    """RMS of residual/σ over triads, samples and axes, ignoring masked (NaN) samples; σ (K, 3) per
    triad and axis or (K, N, 3) per sample (a motion-dependent noise model)."""
    r = np.asarray(residual, float)
    sg = _per_sample(sigma)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(sg > 0, r / sg, np.nan)
    w = w[np.isfinite(w)]
    return float(np.sqrt(np.mean(w ** 2))) if w.size else float("nan")


def residuals_title(residual: np.ndarray, sigma: np.ndarray) -> str:
    return f"Accelerometer residuals over time: RMS of residual/σ {whitened_rms(residual, sigma):.3f}"


def residuals_over_time(t: np.ndarray, residual: np.ndarray, sigma: np.ndarray, names: Sequence[str]) -> Figure:
    """Whitened accelerometer residuals of a dynamic calibration over time, and their RMS per triad.

    Parameters
    ----------
    t
        (N,) sample times, s.
    residual
        (K, N, 3) residual y − model, m/s²; NaN where a sample was masked (saturated).
    sigma
        (K, 3) noise σ per triad and axis, the same for every sample, or (K, N, 3) sample by sample
        (a motion-dependent noise model's σ_n), m/s².
    names
        The K triad names.

    One heatmap per sensor axis (triads × time) of residual/σ on a diverging scale symmetric around
    0, masked samples grey; below, the residual RMS per triad and axis in mm/s² with the noise σ as
    black ticks (with per-sample σ's their RMS over the unmasked samples). The title gives the RMS of
    residual/σ over everything (≈ 1 for a consistent fit).
    """
    import warnings

    t = np.asarray(t, float)
    r = np.asarray(residual, float)
    full = _per_sample(sigma)
    names = list(names)
    K, N, _ = r.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(full > 0, r / full, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a triad masked throughout has no RMS
        # the σ tick per triad and axis: the RMS σ over the samples the residual RMS is taken over
        sg = np.sqrt(np.nanmean(np.where(np.isfinite(r), np.broadcast_to(full, r.shape) ** 2, np.nan), axis=1)) \
            if full.shape[1] > 1 else full[:, 0, :]
    finite = np.abs(w[np.isfinite(w)])
    vmax = max(3.0, float(np.quantile(finite, 0.995))) if finite.size else 3.0
    clipped = bool(finite.size and finite.max() > vmax)
    cmap = plt.get_cmap("RdBu_r").with_extremes(bad="#bdbdbd")
    dt = float(np.median(np.diff(t))) if N > 1 else 1.0
    extent = (t[0] - dt / 2, t[-1] + dt / 2, K - 0.5, -0.5) if N else (0, 1, K - 0.5, -0.5)

    heat_h = max(1.2, 0.085 * K + 0.55)
    fig = _new_figure(11.0, 3 * heat_h + 3.4)
    gs = fig.add_gridspec(4, 1, height_ratios=[heat_h] * 3 + [2.8])
    axes = [fig.add_subplot(gs[0])]
    axes += [fig.add_subplot(gs[k], sharex=axes[0]) for k in (1, 2)]
    step = 1 if K <= 12 else int(np.ceil(K / 12))
    im = None
    for k, ax in enumerate(axes):
        im = ax.imshow(w[:, :, k], cmap=cmap, vmin=-vmax, vmax=vmax, aspect="auto", extent=extent,
                       interpolation="nearest" if N <= 3000 else "antialiased")
        ax.set_yticks(np.arange(0, K, step))
        ax.set_yticklabels(names[::step], fontsize=8 if K > 8 else None)
        ax.set_ylabel(f"{AXES[k]} axis\ntriad", fontsize=9)
        if k < 2:
            ax.tick_params(labelbottom=False)
    axes[-1].set_xlabel("time [s]")
    cb = fig.colorbar(im, ax=axes, extend="both" if clipped else "neither", fraction=0.03, pad=0.01)
    cb.set_label("residual / σ  (grey: masked)")

    ax = fig.add_subplot(gs[3])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a triad masked throughout has no RMS
        rms = np.sqrt(np.nanmean(r ** 2, axis=1)) * 1e3  # (K, 3) mm/s^2
    x = np.arange(K)
    width = 0.8 / 3
    for k in range(3):
        ax.bar(x + (k - 1) * width, rms[:, k], width, color=AXIS_COLORS[k], label=f"{AXES[k]} axis")
        ax.hlines(sg[:, k] * 1e3, x + (k - 1.5) * width, x + (k - 0.5) * width, color="k", lw=1.5,
                  label="noise σ" if k == 0 else None)
    _triad_ticks(ax, names)
    pad = max(0.6, (4 - K) / 2 + 0.1)
    ax.set_xlim(-pad, K - 1 + pad)
    ax.set_ylabel("residual RMS [mm/s²]")
    ax.set_title("Residual RMS over time per triad and axis (black: noise σ)", fontsize=10)
    ax.legend(ncols=4, fontsize=8, loc="upper left", frameon=False)
    top = np.nanmax(np.concatenate([rms.ravel(), sg.ravel() * 1e3])) if K else 1.0
    ax.set_ylim(0, top * 1.35 if np.isfinite(top) and top > 0 else 1)
    ax.grid(axis="y", alpha=0.3)
    fig.suptitle(residuals_title(residual, sigma))
    return fig


def diagnose_residuals(t: np.ndarray, before: dict[str, np.ndarray], after: dict[str, np.ndarray]) -> Figure:
    """Whitened residuals over time, before and after a diagnosis.

    Parameters
    ----------
    t
        (n,) pose mid-times or sample times, s.
    before, after
        Sensor name -> (M, n, 3) residual/σ of every triad, pose or sample and axis (NaN where masked).

    One row per sensor, before left and after right, on a shared y scale per row: every triad and
    axis as a thin line over time (axis colours), so drifts and common-mode patterns stand out; the
    title gives the RMS of residual/σ.
    """
    sensors = [s for s in before if before[s].size]
    fig = _new_figure(11.0, 2.9 * len(sensors) + 0.4)
    axs = fig.subplots(len(sensors), 2, squeeze=False, sharex=True)
    order = np.argsort(t, kind="stable")
    for i, s in enumerate(sensors):
        lim = max(3.0, float(np.nanquantile(np.abs(before[s]), 0.999)), float(np.nanquantile(np.abs(after[s]), 0.999))) * 1.05
        for j, (label, w) in enumerate((("before", before[s]), ("after", after[s]))):
            ax = axs[i, j]
            for m in range(w.shape[0]):
                for k in range(3):
                    ax.plot(t[order], w[m, order, k], color=AXIS_COLORS[k], lw=0.8 if len(t) <= 200 else 0.3, alpha=0.6,
                            marker="." if len(t) <= 200 else None, ms=3)
            ax.axhline(0, color="k", lw=0.6)
            ax.set_ylim(-lim, lim)
            ax.set_title(f"{s} {label}: RMS of residual/σ {np.sqrt(np.nanmean(w ** 2)):.3g}", fontsize=10)
            ax.grid(alpha=0.3)
            if j == 0:
                ax.set_ylabel("residual / σ")
            if i == len(sensors) - 1:
                ax.set_xlabel("time [s]")
    handles = [Line2D([], [], color=c, lw=1.5, label=f"{a} axis") for a, c in zip(AXES, AXIS_COLORS)]
    fig.legend(handles=handles, loc="outside upper center", ncols=3, frameon=False, fontsize=9)
    return fig


def sample_ages(names: Sequence[str], t: np.ndarray, age: np.ndarray, weight: np.ndarray, freqs: np.ndarray,
                power: np.ndarray, fitted: np.ndarray, window: float = 10.0) -> Figure:
    """The sample age each triad's residuals imply (issue 11), and its periodogram.

    Parameters
    ----------
    names
        K triads.
    t
        (n,) sample times, s.
    age, weight, fitted
        (K, n) implied age [s], its weight (1/variance) and the best chip-clock sawtooth [s].
    freqs, power
        (K, F) periodogram frequencies [Hz] and the fraction of the age's variance a sinusoid explains.

    Left: per triad (one row each, offset), the implied age over the first ``window`` seconds,
    weighted-averaged over 3 samples, with the fitted sawtooth; right: the periodogram. A clock beat
    shows as a sawtooth and a peak with harmonics, a drift as a trend, a delay as an offset from zero.
    """
    K = len(names)
    fig = _new_figure(11.0, 0.55 * K + 1.6)
    ax_t, ax_f = fig.subplots(1, 2, width_ratios=(1.6, 1))
    show = t <= t[0] + window
    kernel = np.ones(3)
    step = max(float(np.nanquantile(np.abs(fitted), 0.99)) * 2.5 if fitted.size else 0.0, 1e-4)
    for k, n in enumerate(names):
        w = np.convolve(weight[k], kernel, "same")
        a = np.convolve(weight[k] * age[k], kernel, "same") / np.where(w > 0, w, np.nan)
        off = (K - 1 - k) * step
        ax_t.plot(t[show], (a[show] + off) * 1e3, color=AFTER_COLOR, lw=0.8)
        ax_t.plot(t[show], (fitted[k, show] + off) * 1e3, color="#d62728", lw=0.6, alpha=0.7)
        ax_f.plot(freqs[k], power[k] + (K - 1 - k), color=AFTER_COLOR, lw=0.6)
    ax_t.set_yticks(np.arange(K)[::-1] * step * 1e3)
    ax_t.set_yticklabels(names)
    ax_t.set_xlabel("time [s]")
    ax_t.set_title(f"implied sample age (rows {step * 1e3:.2g} ms apart), fitted sawtooth in red", fontsize=10)
    ax_f.set_yticks(np.arange(K)[::-1])
    ax_f.set_yticklabels(names)
    ax_f.set_xscale("log")
    ax_f.set_xlabel("frequency [Hz]")
    ax_f.set_title("periodogram (variance fraction, rows 1 apart)", fontsize=10)
    for ax in (ax_t, ax_f):
        ax.grid(alpha=0.3)
    return fig

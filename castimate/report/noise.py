"""The Allan deviation figure of a noise characterisation (``castimate noise``)."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from ..kinds.noise import NoiseOutcome

AXIS_COLORS = ("#1f77b4", "#2ca02c", "#d62728")  # x, y, z


def allan_figure(outcome: NoiseOutcome, triad: str) -> Figure:
    """σ(τ) of one triad's accelerometer and gyroscope, per axis, with the fitted N/√τ and K√(τ/3) lines."""
    sensors = [("accelerometer", outcome.accelerometer[triad], "m/s²")]
    if triad in outcome.gyroscope:
        sensors.append(("gyroscope", outcome.gyroscope[triad], "rad/s"))
    fig = Figure(figsize=(5.2 * len(sensors), 3.6), layout="constrained")
    for ax, (name, r, unit) in zip(fig.subplots(1, len(sensors), squeeze=False)[0], sensors):
        for c, (label, color, t) in enumerate(zip("xyz", AXIS_COLORS, r.terms)):
            ax.loglog(r.tau, r.adev[:, c], color=color, label=f"{label}: N={t.noise_density:.2g}, "
                                                               f"B={t.bias_instability:.2g}, K={t.random_walk:.2g}"
                                                               + ("" if t.random_walk_resolved else " (bound)"))
            ax.loglog(r.tau, t.noise_density / np.sqrt(r.tau), color=color, lw=0.7, ls=":")
            if t.random_walk_resolved:
                ax.loglog(r.tau, t.random_walk * np.sqrt(r.tau / 3), color=color, lw=0.7, ls="--")
        ax.set_xlabel("cluster time τ [s]")
        ax.set_ylabel(f"Allan deviation [{unit}]")
        ax.set_title(f"{triad} {name}")
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=7)
    return fig

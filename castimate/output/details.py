"""The arrays a report needs, saved beside results.json as ``details.npz`` (SI units)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..io.atomic import write_atomic


def write_details(path: Path, outcome) -> None:
    """Per-pose arrays of a static outcome: readings, σ, residuals, gravity-norm errors, consistency."""
    names = outcome.config.names
    avg = outcome.averages
    arrays = {
        "triads": np.array(names),
        "t_start": avg.t_start, "t_end": avg.t_end, "n": avg.n,
        "acc_mean": np.stack([avg.acc_mean[n] for n in names]),  # (M, P, 3) m/s^2
        "acc_sigma": np.stack([avg.acc_sigma[n] for n in names]),
        "residual_acc": np.stack([outcome.residual_acc[n] for n in names]),  # (M, P, 3) m/s^2
        "norm_error_before": np.stack([outcome.gravity_norm_error[n][0] for n in names]),  # (M, P)
        "norm_error_after": np.stack([outcome.gravity_norm_error[n][1] for n in names]),
    }
    if outcome.residual_gyro:
        g = list(outcome.residual_gyro)
        arrays["gyro_triads"] = np.array(g)
        arrays["residual_gyro"] = np.stack([outcome.residual_gyro[n] for n in g])
    if outcome.consistency is not None:
        arrays["consistency_before"] = outcome.consistency.before
        arrays["consistency_after"] = outcome.consistency.after
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    write_atomic(path, buf.getvalue())


def write_dynamic_details(path: Path, outcome) -> None:
    """Time series of a dynamic outcome: motion estimate, residuals per triad, positions."""
    names = outcome.config.names
    v = outcome.solution.values
    arrays = {
        "triads": np.array(names), "t": outcome.data.t,
        "omega": v["motion.omega"], "omega_dot": v["motion.omega_dot"], "s": v["motion.s"],
        "residual_acc": np.stack([outcome.residual_acc[n] for n in names]),  # (K, N, 3) m/s^2, NaN = masked
        "acc_sigma": np.stack([outcome.data.acc_sigma[n] for n in names]),
        "position": np.stack([outcome.positions[n][0] for n in names]),
        "position_std": np.stack([outcome.positions[n][1] for n in names]),
        "nominal_position": np.stack([outcome.nominal[n] for n in names]),
    }
    if outcome.residual_gyro:
        g = list(outcome.residual_gyro)
        arrays["gyro_triads"] = np.array(g)
        arrays["residual_gyro"] = np.stack([outcome.residual_gyro[n] for n in g])
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    write_atomic(path, buf.getvalue())

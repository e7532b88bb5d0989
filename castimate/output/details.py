"""The arrays a report needs, saved beside results.json as ``details.npz`` (SI units)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..errors import InputError

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
        arrays["gyro_sigma"] = np.stack([outcome.data.gyro_sigma[n] for n in g])
    # the motion-dependent noise model's σ of every reading (castimate.solver.motion_noise), where fitted
    if outcome.data.sigma_sample.get("acc"):
        arrays["acc_sigma_sample"] = np.stack([outcome.data.sigma("acc", n) for n in names])  # (K, N, 3) m/s^2
    if outcome.residual_gyro and outcome.data.sigma_sample.get("gyro"):
        arrays["gyro_sigma_sample"] = np.stack([outcome.data.sigma("gyro", n) for n in g])  # (G, N, 3) rad/s
    buf = io.BytesIO()
    # not compressed: the residuals and σ's are noise that deflate hardly shrinks (MIMU4444 exp_1:
    # 5.04 MB compressed against 5.41 MB stored), and compressing took 0.2 s CPU of a 6376-sample solve
    np.savez(buf, **arrays)
    write_atomic(path, buf.getvalue())


#: The arrays of details.npz by kind, with symbolic dimensions (M triads, P poses, N samples, G triads
#: with gyroscopes) bound from the first array that has them and checked against the others.
DETAILS_SHAPES = {
    "static_array": {"triads": ("M",), "t_start": ("P",), "t_end": ("P",), "n": ("P",),
                     "acc_mean": ("M", "P", 3), "acc_sigma": ("M", "P", 3), "residual_acc": ("M", "P", 3),
                     "norm_error_before": ("M", "P"), "norm_error_after": ("M", "P"), "gyro_triads": ("G",),
                     "residual_gyro": ("G", "P", 3), "consistency_before": ("P",), "consistency_after": ("P",)},
    "dynamic_array": {"triads": ("M",), "t": ("N",), "omega": ("N", 3), "omega_dot": ("N", 3), "s": ("N", 3),
                      "residual_acc": ("M", "N", 3), "acc_sigma": ("M", 3), "position": ("M", 3),
                      "position_std": ("M", 3), "nominal_position": ("M", 3), "gyro_triads": ("G",),
                      "residual_gyro": ("G", "N", 3), "gyro_sigma": ("G", 3), "acc_sigma_sample": ("M", "N", 3),
                      "gyro_sigma_sample": ("G", "N", 3)},
}
DETAILS_SHAPES["ferraris"] = DETAILS_SHAPES["static_array"]  # the six faces are its poses
#: Arrays of text (triad names); all others are numbers.
DETAILS_NAMES = ("triads", "gyro_triads")


def check_details(arrays: dict[str, np.ndarray], kind: str, triads: list[str], path: Path,
                  required: tuple[str, ...]) -> dict[str, np.ndarray]:
    """details.npz's arrays: the required ones present, numbers (names: text), shapes consistent with each
    other and with the triads of results.json. Raises InputError naming the array."""
    dims: dict[str, int] = {"M": len(triads)}
    for key, shape in DETAILS_SHAPES[kind].items():
        if key not in arrays:
            if key in required:
                raise InputError(path, key, "array missing; re-run `castimate solve` to regenerate details.npz")
            continue
        a = arrays[key]
        text = key in DETAILS_NAMES
        if (a.dtype.kind in "US") != text or (not text and a.dtype.kind not in "biuf"):
            raise InputError(path, key, f"expected {'names' if text else 'numbers'}, found an array of dtype {a.dtype}")
        if a.ndim != len(shape) or any(isinstance(d, int) and a.shape[i] != d for i, d in enumerate(shape)):
            raise InputError(path, key, f"expected shape ({', '.join(map(str, shape))}), found {a.shape}")
        for i, d in enumerate(shape):
            if isinstance(d, str) and dims.setdefault(d, a.shape[i]) != a.shape[i]:
                raise InputError(path, key, f"expected {dims[d]} along axis {i} ({d}: "
                                            f"{'triads' if d == 'M' else 'the other arrays'}), found shape {a.shape}")
    if "triads" in arrays and [str(x) for x in arrays["triads"]] != list(triads):
        raise InputError(path, "triads", f"expected the triads of results.json ({', '.join(triads)}), found "
                                         f"{', '.join(map(str, arrays['triads']))}")
    return arrays


def check_pairing(arrays: dict[str, np.ndarray], results: dict, path: Path) -> None:
    """Refuse a details.npz that does not belong to the results.json beside it (one copied from another
    solve's directory): the number of poses or samples and each triad's residual RMS per axis, which
    results.json records from the same residuals, must agree."""
    count = (results.get("poses") or {}).get("count") if results.get("kind") != "dynamic_array" \
        else results.get("samples")
    key = "t" if results.get("kind") == "dynamic_array" else "t_start"
    if isinstance(count, int) and key in arrays and len(arrays[key]) != count:
        raise InputError(path, key, f"expected {count} {'samples' if key == 't' else 'poses'} as in results.json, "
                                    f"found {len(arrays[key])}: details.npz of another solve (re-run `castimate solve`)")
    rms = (results.get("residuals") or {}).get("rms")
    if not isinstance(rms, dict) or "residual_acc" not in arrays or "triads" not in arrays:
        return
    with np.errstate(invalid="ignore"):
        found = np.sqrt(np.nanmean(arrays["residual_acc"] ** 2, axis=1))
    for name, row in zip(arrays["triads"], found):
        want = rms.get(str(name))
        try:
            want = np.asarray(want, float)
        except (TypeError, ValueError):
            continue
        if want.shape == row.shape and not np.allclose(row, want, rtol=1e-6, atol=1e-12, equal_nan=True):
            raise InputError(path, "residual_acc", f"the residual RMS of {name} is {np.round(row, 9).tolist()}, where "
                                                   f"results.json has {np.round(want, 9).tolist()}: details.npz of "
                                                   "another solve (re-run `castimate solve`)")

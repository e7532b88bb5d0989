"""Ground-truth Ferraris sessions (six faces, three turns) in imucal's file format.

Independent of the estimator: the faces are exact, each turn is a raised-cosine rotation about the
face's up axis with the rate in closed form, sampled at the middle of each sample interval.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .static import StaticTruth

FACE_UP = {"x_p": (1, 0, 0), "x_a": (-1, 0, 0), "y_p": (0, 1, 0), "y_a": (0, -1, 0), "z_p": (0, 0, 1), "z_a": (0, 0, -1)}
TURN_AXIS = {"x_rot": (1, 0, 0), "y_rot": (0, 1, 0), "z_rot": (0, 0, 1)}


def ferraris_session(truth: StaticTruth, rng: np.random.Generator, *, rate: float = 102.4, hold: float = 5.0,
                     turn: float = 3.0, angle_deg: float = -360.0, sigma: float = 0.02, gyro_sigma: float = 0.005,
                     name: str = "imu") -> tuple[dict[str, np.ndarray], dict[str, dict[str, int]]]:
    """(columns of imucal's table, imucal's section list) of one simulated session.

    Each face is held ``hold`` s (its section: the middle 80 %); each turn lasts ``turn`` s inside a
    hold of the face it starts from, its section covering the turn with a second of rest either side.
    Readings: T g u + b (accelerometer, m/s^2) and T_g ω + b_g (gyroscope), in °/s for the table.
    """
    up, omega, sections, k = [], [], {}, 0
    n_hold, n_turn = int(round(hold * rate)), int(round(turn * rate))
    pad = int(round(rate))
    for label, u in FACE_UP.items():
        up.append(np.tile(u, (n_hold, 1)))
        omega.append(np.zeros((n_hold, 3)))
        sections[label] = {"start": k + n_hold // 10, "end": k + n_hold - n_hold // 10}
        k += n_hold
    for label, a in TURN_AXIS.items():
        a = np.asarray(a, float)
        t_mid = (np.arange(n_turn + 2 * pad) - pad + 0.5) / rate  # sample midpoints relative to the turn start
        x = np.clip(t_mid / turn, 0, 1)
        sdot = np.where((t_mid > 0) & (t_mid < turn), 0.5 * np.pi / turn * np.sin(np.pi * x), 0.0)
        up.append(np.tile(a, (len(t_mid), 1)))
        omega.append(np.radians(angle_deg) * sdot[:, None] * a[None])
        sections[label] = {"start": k, "end": k + len(t_mid)}
        k += len(t_mid)
    U, W = np.vstack(up), np.vstack(omega)
    acc = truth.gravity * U @ truth.T(name).T + truth.b(name) + sigma * rng.standard_normal(U.shape)
    gyro = W @ truth.Tg(name).T + truth.values[f"{name}.gyroscope.bias"] + gyro_sigma * rng.standard_normal(U.shape)
    gd = np.degrees(gyro)
    cols = {"n_samples": np.arange(len(U)), "gyr_x": gd[:, 0], "gyr_y": gd[:, 1], "gyr_z": gd[:, 2],
            "acc_x": acc[:, 0], "acc_y": acc[:, 1], "acc_z": acc[:, 2]}
    return cols, sections


def write_imucal(directory: Path, cols: dict[str, np.ndarray], sections: dict) -> tuple[Path, Path]:
    """session.csv and sections.json in imucal's formats."""
    directory.mkdir(parents=True, exist_ok=True)
    csv, js = directory / "session.csv", directory / "sections.json"
    names = list(cols)
    rows = np.column_stack([cols[c] for c in names])
    csv.write_text(",".join(names) + "\n" + "\n".join(",".join([str(int(r[0]))] + [repr(float(v)) for v in r[1:]])
                                                      for r in rows) + "\n")
    js.write_text(json.dumps(sections))
    return csv, js

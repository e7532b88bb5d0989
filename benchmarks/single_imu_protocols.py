"""Single-IMU protocols on the shared real sessions, side by side with what users compare against.

1. The imu_tk Xsens session (Tedaldi 2014 multi-position protocol, problems/xsens_imutk_gyro.yaml):
   castimate's accelerometer and gyroscope (from the rotations between poses) against the
   manufacturer's nominal offsets and scales in the data README.
2. The imucal Ferraris session (problems/imucal_ferraris.yaml): castimate's ``kind: ferraris``
   against imucal's own FerrarisCalibration on the same data and section list. Both are also
   scored on data neither fitted: the five hand rotations between consecutive faces, integrated
   with each calibration (exact per-sample exponential), must carry one face's calibrated gravity
   direction onto the next's.
3. Noise: Allan deviation of the Xsens session's static segments (castimate noise).

imucal is a benchmark peer, not a castimate dependency. Install it into the environment first:

    pip install imucal          # 2.6.0 was measured

Run from the repository root: ``python benchmarks/single_imu_protocols.py``. Writes
results/single_imu_protocols.{json,md}; takes about a minute (most of it the Xsens solve).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from castimate.kinds import calibrate  # noqa: E402
from castimate.kinds.noise import characterise_noise  # noqa: E402
from castimate.io.imucal import read_sections  # noqa: E402
from castimate.spec import load_problem  # noqa: E402

OUT = ROOT / "benchmarks" / "results"
XSENS_NOMINAL = {"acc_offset": [33123, 33276, 32360], "acc_scale": [415, 413, 415],
                 "gyro_offset": [32768, 32466, 32485], "gyro_scale": [4778, 4758, 4766]}


def rotate_back(w, u):
    th = np.linalg.norm(w)
    if th < 1e-15:
        return u
    wu = np.cross(w, u)
    return u - np.sin(th) / th * wu + (1 - np.cos(th)) / th ** 2 * np.cross(w, wu)


def xsens():
    spec = load_problem(ROOT / "problems" / "xsens_imutk_gyro.yaml")
    t0 = time.perf_counter()
    out = calibrate(spec)
    wall = time.perf_counter() - t0
    ua, ug = spec.data.acc_units, spec.data.gyro_units
    Ta, ba = out.calibration["imu"]
    Tg, bg = out.gyro_calibration["imu"]
    row = {"acc_offset": (ua.offset + ba / ua.scale).tolist(), "acc_scale": (np.diag(Ta) / ua.scale).tolist(),
           "gyro_offset": (ug.offset + bg / ug.scale).tolist(), "gyro_scale": (np.diag(Tg) / ug.scale).tolist()}
    sd = out.solution.std
    return {"castimate": row, "nominal": XSENS_NOMINAL, "poses": out.averages.n_poses,
            "chi2_per_dof": out.solution.chi2_per_dof, "wall_s": wall,
            "gyro_gain_std": sd["imu.gyroscope.gain"].tolist(),
            "gyro_misalignment_deg": np.degrees(out.solution.values["imu.gyroscope.misalignment"]).tolist(),
            "gravity_norm_rms_mm_s2": float(1e3 * np.sqrt(np.mean(out.gravity_norm_error["imu"][1] ** 2)))}


def imucal_peer(csv, sections, rate):
    import pandas as pd
    from imucal import FerrarisCalibration, ferraris_regions_from_section_list

    data = pd.read_csv(csv)
    section_list = pd.DataFrame(json.loads(Path(sections).read_text())).T
    regions = ferraris_regions_from_section_list(data, section_list)
    t0 = time.perf_counter()
    info = FerrarisCalibration().compute(regions, sampling_rate_hz=rate, from_acc_unit="m/s^2", from_gyr_unit="deg/s")
    wall = time.perf_counter() - t0
    return info, data, wall


def ferraris():
    spec = load_problem(ROOT / "problems" / "imucal_ferraris.yaml")
    t0 = time.perf_counter()
    out = calibrate(spec)
    wall = time.perf_counter() - t0
    info, df, wall_peer = imucal_peer(spec.data.path, spec.data.sections, spec.data.rate)
    import imucal

    Ta, ba = out.calibration["imu"]
    Tg, bg = out.gyro_calibration["imu"]
    mine = {"T_a": Ta, "b_a": ba, "T_g": Tg, "b_g_deg_s": np.degrees(bg)}
    peer = {"T_a": info.K_a @ info.R_a, "b_a": info.b_a, "T_g": info.K_g @ info.R_g, "b_g_deg_s": info.b_g}
    acc = df[["acc_x", "acc_y", "acc_z"]].to_numpy()
    gyr = df[["gyr_x", "gyr_y", "gyr_z"]].to_numpy()
    f_mine = np.linalg.solve(Ta, (acc - ba).T).T
    w_mine = np.linalg.solve(Tg, (np.radians(gyr) - bg).T).T
    f_peer, w_peer_deg = info.calibrate(acc, gyr, "m/s^2", "deg/s")
    sec = read_sections(spec.data.sections)
    faces = ["x_p", "x_a", "y_p", "y_a", "z_p", "z_a"]
    dt = 1 / spec.data.rate

    def scores(f, w):
        norm = [abs(np.linalg.norm(f[a:b].mean(axis=0)) - 9.81) * 1e3 for a, b in (sec[k] for k in faces)]
        held = []
        for k0, k1 in zip(faces[:-1], faces[1:]):
            (a0, b0), (a1, b1) = sec[k0], sec[k1]
            u = f[a0:b0].mean(axis=0)
            u /= np.linalg.norm(u)
            for k in range(b0, a1):
                u = rotate_back(w[k] * dt, u)
            v = f[a1:b1].mean(axis=0)
            held.append(float(np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v)), u @ v / np.linalg.norm(v)))))
        turns = []
        for k in ("x_rot", "y_rot", "z_rot"):
            a, b = sec[k]
            turns.append(float(np.degrees(np.linalg.norm(w[a:b].sum(axis=0) * dt))))
        return {"gravity_norm_error_mm_s2": norm, "held_out_transition_error_deg": held, "turn_angles_deg": turns}

    return {"castimate": {k: np.asarray(v).tolist() for k, v in mine.items()},
            "imucal": {k: np.asarray(v).tolist() for k, v in peer.items()},
            "imucal_version": imucal.__version__ if hasattr(imucal, "__version__") else "?",
            "scores": {"castimate": scores(f_mine, w_mine), "imucal": scores(f_peer, np.radians(w_peer_deg))},
            "wall_s": {"castimate": wall, "imucal": wall_peer}, "chi2_per_dof": out.solution.chi2_per_dof}


def noise():
    out = characterise_noise(load_problem(ROOT / "problems" / "xsens_imutk.yaml"))
    def terms(r):
        return {ax: {"N": t.noise_density, "B": t.bias_instability, "K": t.random_walk, "K_resolved": t.random_walk_resolved}
                for ax, t in zip("xyz", r.terms)}
    a, g = out.accelerometer["imu"], out.gyroscope["imu"]
    return {"duration_s": a.duration, "longest_s": a.longest, "accelerometer": terms(a), "gyroscope": terms(g)}


def fmt3(v, p=4):
    return "[" + ", ".join(f"{x:.{p}g}" for x in v) + "]"


def main():
    load = open("/proc/loadavg").read().split()[:3]
    res = {"loadavg": load, "xsens": xsens(), "ferraris": ferraris(), "noise": noise()}
    x, fe, nz = res["xsens"], res["ferraris"], res["noise"]
    md = [f"# Single-IMU protocols on the shared sessions (load average {' '.join(load)})", "",
          f"## Xsens (imu_tk session, {x['poses']} poses; χ²/dof {x['chi2_per_dof']:.1f}; solve {x['wall_s']:.1f} s)", "",
          "| quantity | castimate | nominal (data README) | difference |", "|---|---|---|---|"]
    for k in ("acc_offset", "acc_scale", "gyro_offset", "gyro_scale"):
        c, n = np.array(x["castimate"][k]), np.array(x["nominal"][k])
        diff = fmt3(c - n, 3) + " counts" if "offset" in k else fmt3(100 * (c / n - 1), 3) + " %"
        md.append(f"| {k.replace('_', ' ')} | {fmt3(c, 6)} | {fmt3(n, 6)} | {diff} |")
    md += ["", f"Gyroscope misalignment {fmt3(x['gyro_misalignment_deg'], 3)} deg; gain σ {fmt3(x['gyro_gain_std'], 2)}; "
               f"gravity-norm error RMS after calibration {x['gravity_norm_rms_mm_s2']:.2f} mm/s².", "",
           f"## imucal Ferraris session: castimate vs imucal {fe['imucal_version']}", "",
           "| quantity | castimate | imucal |", "|---|---|---|"]
    for k in ("T_a", "b_a", "T_g", "b_g_deg_s"):
        c, p = np.array(fe["castimate"][k]), np.array(fe["imucal"][k])
        if c.ndim == 2:
            for i in range(3):
                md.append(f"| {k} row {i} | {fmt3(c[i], 5)} | {fmt3(p[i], 5)} |")
        else:
            md.append(f"| {k} | {fmt3(c, 4)} | {fmt3(p, 4)} |")
    for name, key, unit in (("face |f| - g", "gravity_norm_error_mm_s2", "mm/s²"),
                            ("held-out transitions", "held_out_transition_error_deg", "deg"),
                            ("turn angles", "turn_angles_deg", "deg")):
        c, p = fe["scores"]["castimate"][key], fe["scores"]["imucal"][key]
        md.append(f"| {name} [{unit}] | {fmt3(c, 3)} (RMS {np.sqrt(np.mean(np.square(c))):.3g}) | "
                  f"{fmt3(p, 3)} (RMS {np.sqrt(np.mean(np.square(p))):.3g}) |")
    md += ["", f"castimate {fe['wall_s']['castimate']:.2f} s (including the first build), imucal {fe['wall_s']['imucal']:.3f} s; "
               f"castimate χ²/dof {fe['chi2_per_dof']:.0f}.", "",
           f"## Noise (Allan deviation of the Xsens static segments, {nz['duration_s']:.0f} s, longest {nz['longest_s']:.0f} s)", "",
           "| sensor | axis | N (/√Hz) | B | K (√Hz/s) |", "|---|---|---|---|---|"]
    for s in ("accelerometer", "gyroscope"):
        for ax, t in nz[s].items():
            md.append(f"| {s} | {ax} | {t['N']:.3g} | {t['B']:.3g} | {t['K']:.3g}{'' if t['K_resolved'] else ' (bound)'} |")
    text = "\n".join(md) + "\n"
    print(text)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "single_imu_protocols.json").write_text(json.dumps(res, indent=1))
    (OUT / "single_imu_protocols.md").write_text(text)


if __name__ == "__main__":
    main()

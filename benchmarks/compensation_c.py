"""The generated C compensation against Calibration.apply, per effect (issue 14's acceptance:
1e-12 in double, 1e-5 relative in float, with every effect).

For each sample-wise registry effect alone, and all of them together, a two-triad results.json with
random coefficients at 10x their realistic magnitude (simulate/effects.py), a counts input
conversion and a temperature in degC counts is written; ``castimate codegen`` emits the C,
``make check`` runs the 305 test vectors (spread over the session's time and ±5 K) through the
double, double-with-parameter-array and float variants. Prints the table and writes
benchmarks/results/compensation_c.md.

    python benchmarks/compensation_c.py
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from castimate.codegen import generate_c  # noqa: E402
from castimate.problem.effects import EFFECTS  # noqa: E402
from castimate.simulate.effects import REALISTIC_DYNAMIC_EFFECTS, REALISTIC_EFFECTS, random_coefficients  # noqa: E402

COUNTS = {"accelerometer": {"unit": "counts", "scale": [9.80665 / 2048] * 3, "offset": [0.0] * 3, "scale_unit": "m/s^2"},
          "gyroscope": {"unit": "counts", "scale": [np.pi / 180 / 16.4] * 3, "offset": [0.0] * 3, "scale_unit": "rad/s"},
          "temperature": {"unit": "counts", "scale": 1.0, "offset": -273.15, "scale_unit": "K"}}


def results_doc(keys, rng) -> dict:
    magnitude = {**REALISTIC_EFFECTS, **REALISTIC_DYNAMIC_EFFECTS}
    triads = {}
    for n, R in (("imu1", np.eye(3)), ("imu2", np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]))):
        params = {(e.name if e.sensor == "accelerometer" else e.key):
                  {"value": random_coefficients(e.key, 10 * magnitude[e.key], rng).tolist()}
                  for e in EFFECTS if e.key in keys}
        triads[n] = {"accelerometer": {"T": ((np.eye(3) + 0.01 * rng.standard_normal((3, 3))) @ R).tolist(),
                                       "b": (0.2 * rng.standard_normal(3)).tolist()},
                     "gyroscope": {"T": ((np.eye(3) + 0.01 * rng.standard_normal((3, 3))) @ R).tolist(),
                                   "b": (0.02 * rng.standard_normal(3)).tolist()},
                     "R_nominal": R.tolist(), "parameters": params}
    return {"format": "castimate.results/1", "status": {"success": True}, "triads": triads,
            "units": {"data_format": "mimu", "input": COUNTS},
            "effects": {"included": [e.key for e in EFFECTS if e.key in keys],
                        "regressors": {"time": {"t_mid_s": 250.0, "t_half_s": 240.0},
                                       "temperature_mean_K": {"imu1": 300.0, "imu2": 303.0}}}}


def run(keys) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "results.json"
        src.write_text(json.dumps(results_doc(keys, np.random.default_rng(7))))
        generate_c(src, Path(tmp) / "c")
        p = subprocess.run(["make", "-C", str(Path(tmp) / "c"), "check"], capture_output=True, text=True)
        found = re.findall(r"(castimate_compensate\w*): max abs difference (\S+), max rel difference (\S+)", p.stdout)
        return {"ok": p.returncode == 0, **{v: (float(a), float(r)) for v, a, r in found}}


def main() -> None:
    sample_wise = [e.key for e in EFFECTS if e.sample_wise]
    cases = [[k] for k in sample_wise] + [sample_wise]
    lines = ["| effects | make check | double: max abs | double: max rel | parameter array: max rel | "
             "float: max abs | float: max rel |", "|---|---|---|---|---|---|---|"]
    for keys in cases:
        r = run(keys)
        name = keys[0] if len(keys) == 1 else f"all {len(keys)}"
        lines.append(f"| {name} | {'OK' if r['ok'] else 'FAILED'} | {r['castimate_compensate'][0]:.1e} | "
                     f"{r['castimate_compensate'][1]:.1e} | {r['castimate_compensate_p'][1]:.1e} | "
                     f"{r['castimate_compensatef'][0]:.1e} | {r['castimate_compensatef'][1]:.1e} |")
        print(lines[-1], flush=True)
    text = ("# C compensation vs Calibration.apply (benchmarks/compensation_c.py)\n\n"
            "Relative differences are |C - apply| / max(1, |apply|); 305 vectors per case, 2 triads, counts input.\n\n"
            + "\n".join(lines) + "\n")
    out = ROOT / "benchmarks" / "results" / "compensation_c.md"
    out.write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

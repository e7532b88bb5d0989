"""Simulation scenarios (``castimate simulate SCENARIO.yaml -o DIR``): data, truth and a ready problem."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .errors import InputError
from .io.readers import write_csv
from .io.recording import Recording
from .io.results import write_atomic, write_json
from .problem.spec import _Check
from .simulate import (StaticTruthScale, pose_directions, random_static_truth, static_pose_means,
                       static_time_series)

SCENARIO_KEYS = ("kind", "seed", "gravity", "triads", "reference", "poses", "noise", "samples_per_pose",
                 "truth", "gyroscope", "time_series", "rate", "pose_duration", "transition")


def _flag(c: _Check, s: dict, key: str) -> bool:
    v = s.get(key, False)
    if not isinstance(v, bool):
        c.fail(key, f"expected true or false, found {v!r}")
    return v


def simulate_scenario(path: str | Path, out: str | Path) -> dict[str, Path]:
    """Read a scenario file, simulate it and write ``data.csv``, ``truth.json`` and ``problem.yaml``."""
    path, out = Path(path), Path(out)
    try:
        raw = yaml.safe_load(path.read_text())
    except OSError as e:
        raise InputError(path, "", f"cannot read the scenario file ({e.strerror})") from None
    except yaml.YAMLError as e:
        raise InputError(path, "", f"not valid YAML ({e})") from None
    c = _Check(path)
    s = c.mapping(raw, "", SCENARIO_KEYS, required=("kind",))
    c.choice(s["kind"], "kind", ("static_array",))
    seed = c.number(s.get("seed", 0), "seed", integer=True)
    if seed < 0:
        c.fail("seed", f"expected a non-negative integer, found {seed}")
    rng = np.random.default_rng(seed)
    g = c.number(s.get("gravity", 9.81), "gravity", positive=True)
    tr = s.get("triads", 14)
    if isinstance(tr, list):
        if not tr:
            c.fail("triads", "expected a number of triads or a non-empty list of names, found []")
        names = []
        for i, n in enumerate(tr):
            if not isinstance(n, str) or not n.replace("_", "").isalnum():
                c.fail(f"triads[{i}]", f"expected a name of letters, digits and underscores, found {n!r}")
            if n in names:
                c.fail(f"triads[{i}]", f"duplicate triad name {n!r}")
            names.append(n)
    else:
        names = [f"imu{i + 1}" for i in range(c.number(tr, "triads", positive=True, integer=True))]
    ref = s.get("reference", names[0])
    if ref not in names:
        c.fail("reference", f"unknown triad {ref!r}; triads are {', '.join(names)}")
    P = c.number(s.get("poses", 20), "poses", positive=True, integer=True)
    noise = c.mapping(s.get("noise"), "noise", ("accelerometer", "gyroscope"))
    sigma = c.number(noise.get("accelerometer", 0.01), "noise.accelerometer", positive=True)
    gyro = _flag(c, s, "gyroscope")
    gsigma = c.number(noise.get("gyroscope", 0.002), "noise.gyroscope", positive=True) if gyro else None
    tsec = c.mapping(s.get("truth"), "truth", tuple(StaticTruthScale.__dataclass_fields__))
    scale = StaticTruthScale(**{k: c.number(v, f"truth.{k}") for k, v in tsec.items()})
    for k, v in vars(scale).items():
        if v < 0:
            c.fail(f"truth.{k}", f"expected a standard deviation >= 0, found {v}")
    n_samp = c.number(s.get("samples_per_pose", 1000), "samples_per_pose", positive=True, integer=True)

    truth = random_static_truth(names, ref, rng, g, scale, gyroscope=gyro)
    U = pose_directions(P, rng)
    problem: dict[str, Any] = {
        "kind": "static_array",
        "data": {"path": "data.csv", "format": "csv"},
        "array": {"reference": ref, "triads": [{"name": n} for n in names]},
        "model": {"gravity": g},
    }
    if _flag(c, s, "time_series"):
        rate = c.number(s.get("rate", 100.0), "rate", positive=True)
        rec, intervals = static_time_series(truth, U, sigma, rng, rate=rate,
                                            pose_duration=c.number(s.get("pose_duration", 10.0), "pose_duration", positive=True),
                                            transition=c.number(s.get("transition", 3.0), "transition", positive=True),
                                            gyro_sigma=gsigma)
        problem["data"]["segments"] = "auto"
        problem["noise"] = {"accelerometer": "auto"}
    else:
        acc, gy = static_pose_means(truth, U, sigma, n_samp, rng, gsigma)
        rec = Recording(t=np.arange(P, dtype=float), acc=acc, gyro=gy, source="simulation")
        problem["data"]["segments"] = "rows"
        problem["noise"] = {"accelerometer": sigma / np.sqrt(n_samp)}
        if gyro:
            problem["noise"]["gyroscope"] = gsigma / np.sqrt(n_samp)
        intervals = [(float(i), float(i)) for i in range(P)]
    problem["noise"] = {k: (float(v) if not isinstance(v, str) else v) for k, v in problem["noise"].items()}
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "data.csv", rec)
    doc = truth.to_dict()
    doc.update({"directions": U, "static_intervals_s": intervals, "noise": {"accelerometer": sigma, "gyroscope": gsigma},
                "samples_per_pose": n_samp})
    write_json(out / "truth.json", doc)
    header = f"# Simulated from {path.name}; the truth is in truth.json.\n"
    write_atomic(out / "problem.yaml", header + yaml.safe_dump(problem, sort_keys=False))
    return {"data": out / "data.csv", "truth": out / "truth.json", "problem": out / "problem.yaml"}

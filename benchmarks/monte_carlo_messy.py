#!/usr/bin/env python
"""Dynamic Monte Carlo on the messy simulator (issue 11 item 7), one messy ingredient at a time, on
``castimate montecarlo``'s engine.

``problems/montecarlo_messy_8x1000.yaml`` is the 8-IMU board at 62.5 Hz with everything at once. Each
row here is that scenario with only some ingredients kept, and the estimator with only the matching
effects free (the scenario's ``montecarlo.problem``), default settings otherwise:

=========  ====================================================  ===========================================
row        simulated (besides white noise, smooth motion)        estimator's matching effects
=========  ====================================================  ===========================================
clean      nothing                                               none
rails      int16 counts, both rails at 700 °/s (~5 % samples)    none (both rails masked from the ADC range)
delay      gyroscopes 1 ms behind the accelerometers            gyroscope.delay of every triad
pink       pink (1/f) noise as large as the white               none
clocks     per-chip sawtooth sample ages (~1 kHz chip clocks)   accelerometer.clock_beat
coupling   general 3x3 gyroscope matrices (σ 0.01)              gyroscope gain, misalignment, coupling;
                                                                 biases fixed
all        all of the above                                      all of the above
=========  ====================================================  ===========================================

Every row is scored against the Cramér-Rao bound of the measurements with the motion free per
sample (``montecarlo.bound: measurements``) of its own model: position RMSE/bound, std(error/σ)
with the σ each run reported, failures by reason, CPU time. Rows are written as they finish.

Run: ``PYTHONPATH=. python benchmarks/monte_carlo_messy.py [--runs 50] [--rows clean,rails,...]
[--workers 2]``. Writes ``benchmarks/results/monte_carlo_messy.{json,md}`` (merged with the rows
already there, so rows can be run and rerun separately).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import copy  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import yaml  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from monte_carlo_dynamic import COLUMNS, machine, md_table, row, run_study, summary, text_table  # noqa: E402

from castimate.problem.effects import BY_KEY  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The accelerometer-gyroscope delay's parameter: gyroscope.delay (before it, the rows were run with the
#: per-sensor gyroscope.time_offset of every triad, which, absolute per triad, expressed it as well).
DELAY = "delay" if "gyroscope.delay" in BY_KEY else "time_offset"
SCENARIO = ROOT / "problems" / "montecarlo_messy_8x1000.yaml"
#: The messy ingredients: the scenario keys that simulate each, and the estimator's effects that match it.
INGREDIENTS = {
    "rails": {"scenario": ("adc",), "model": {}},
    "delay": {"scenario": ("delay",), "model": {"gyroscope": {DELAY: "free"}}},
    "pink": {"scenario": ("noise.pink",), "model": {}},
    "clocks": {"scenario": ("effects",), "model": {"accelerometer": {"clock_beat": "free"}}},
    "coupling": {"scenario": ("gyroscope_matrix",),
                 "model": {"gyroscope": {"gain": "free", "misalignment": "free", "coupling": "free", "bias": "fixed"},
                           "triads": {"imu1": {"gyroscope": {"gain": "fixed", "misalignment": "fixed",
                                                              "coupling": "fixed"}}}}},
}
ROWS = {"clean": (), "rails": ("rails",), "delay": ("delay",), "pink": ("pink",), "clocks": ("clocks",),
        "coupling": ("coupling",), "all": tuple(INGREDIENTS)}


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def row_scenario(base: dict, keep: tuple[str, ...]) -> dict:
    """The base scenario with only the ingredients ``keep`` simulated and matched by the estimator."""
    s = copy.deepcopy(base)
    for name, ing in INGREDIENTS.items():
        if name in keep:
            continue
        for key in ing["scenario"]:
            head, _, sub = key.partition(".")
            if sub:
                s.get(head, {}).pop(sub, None)
            else:
                s.pop(key, None)
    model: dict = {}
    for name in keep:
        model = _merge(model, INGREDIENTS[name]["model"])
    s["montecarlo"] = {**s.get("montecarlo", {}), "problem": {"model": model} if model else {}}
    return s


def markdown(rows: dict, info: dict) -> str:
    out = ["# Dynamic Monte Carlo on the messy simulator, one ingredient at a time", "",
           "Generated by `PYTHONPATH=. python benchmarks/monte_carlo_messy.py` on `castimate montecarlo`'s engine. "
           "The 8-IMU board of `problems/montecarlo_messy_8x1000.yaml` (62.5 Hz, 1000 samples, smooth `sinusoids` "
           "motion up to 1000 °/s, 0.04 m/s² and 0.06 °/s white noise), each row with only its ingredients simulated "
           "and the estimator with the matching effects free, default settings otherwise (wiener3 process model, "
           "levels estimated; motion-dependent noise auto). Bound: the Cramér-Rao bound of the row's measurement model "
           "with the motion free per sample. RMSE pooled over runs and the 21 non-reference position components "
           "(± standard error from the bound's correlation); error/σ with the σ each run reported.", "",
           *md_table(["row", *COLUMNS[1:]], [row(name, r) for name, r in rows.items()]), ""]
    for name, r in rows.items():
        fails = "; ".join(f"{k}: {v}" for k, v in r["failures"].items()) or "none"
        first = r["failed_runs"][0]["message"][:300] if r["failed_runs"] else ""
        out.append(f"- {name}: simulated {', '.join(r['ingredients']) or 'white noise only'}; estimator "
                   f"{json.dumps(r['estimator_model']) if r['estimator_model'] else 'default'}; χ²/dof median "
                   f"{r['chi2_per_dof_median']:.3f}; reported σ / bound median "
                   f"{r.get('reported_sigma_over_crb_median', float('nan')):.2f}; {r['wall_s']:.0f} s wall, "
                   f"{r['cpu_s']:.0f} s CPU ({r['run_cpu_s_total']:.0f} s in the runs), {r['workers']} workers, "
                   f"1-min load {r['loadavg_1min'][0]} → {r['loadavg_1min'][1]}; failures: {fails}"
                   + (f" (first: {first})" if first else "") + ".")
    out += ["", "Machine: " + ", ".join(f"{k} {v}" for k, v in info.items()), ""]
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--rows", default=",".join(ROWS))
    ap.add_argument("--workers", type=int, default=2, help="Dask workers (0: in this process)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = ap.parse_args(argv)
    base = yaml.safe_load(SCENARIO.read_text())
    info = machine()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "monte_carlo_messy.json"
    doc = json.loads(path.read_text()) if path.exists() else {"benchmark": "monte_carlo_messy", "rows": {}}
    for name in [x.strip() for x in args.rows.split(",") if x.strip()]:
        scen = row_scenario(base, ROWS[name])
        print(f"== {name}: {args.runs} runs", flush=True)
        with tempfile.TemporaryDirectory(prefix="castimate-messy-") as tmp:
            sc = Path(tmp) / f"messy_{name}.yaml"
            sc.write_text(yaml.safe_dump(scen, sort_keys=False))
            study, timing = run_study(sc, args.runs, args.workers, lambda m: print("  ", m, flush=True))
        r = summary(study, timing)
        r.update({"ingredients": list(ROWS[name]), "estimator_model": scen["montecarlo"]["problem"].get("model", {}),
                  "machine": info, "finished": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())})
        doc["rows"][name] = r
        doc["rows"] = {k: doc["rows"][k] for k in ROWS if k in doc["rows"]}
        path.write_text(json.dumps(doc, indent=2, default=float) + "\n")
        (args.out / "monte_carlo_messy.md").write_text(markdown(doc["rows"], info))
        print(text_table(["row", *COLUMNS[1:]], [row(name, r)]), flush=True)
    print(f"wrote {path} and {args.out / 'monte_carlo_messy.md'}")
    return 0


if __name__ == "__main__":  # Dask's worker processes import this file: run only as a script
    sys.exit(main())

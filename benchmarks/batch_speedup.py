"""Speed-up of castimate batch with 1 and 2 Dask workers, in one run, on 10 simulated boards.

Ten static boards (8 triads, 20 poses, a raw 100 Hz time series of 10 s poses: detection, pose
averages, build and solve per board, each a different truth), calibrated from one problem template
with a LocalCluster of 1 worker, then of 2. Every worker is warmed up first (client.run: it imports
castimate and loads the compiled functions), so the ratio is of the calibrations alone; the mean
time per calibration on a worker shows how much the workers slow each other (a loaded machine). Prints and
writes benchmarks/results/batch_speedup.{json,md}.

    PYTHONPATH=. python benchmarks/batch_speedup.py
"""

import json
import os
import tempfile
import time
from pathlib import Path

import yaml

from castimate.scale.batch import calibrate_recording, load_template, run_batch
from castimate.scale.engine import dask_client
from castimate.simulate.scenarios import simulate_scenario

BOARDS = 10
SCENARIO = {"kind": "static_array", "triads": 8, "poses": 20, "noise": {"accelerometer": 0.02}, "time_series": True,
            "rate": 100, "pose_duration": 10, "transition": 2}


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for k in range(BOARDS):
            sc = tmp / f"board{k}.yaml"
            sc.write_text(yaml.safe_dump({**SCENARIO, "seed": 100 + k}))
            simulate_scenario(sc, tmp / f"board{k:02d}")
        template = tmp / "board00" / "problem.yaml"
        pattern = str(tmp / "board*" / "data.csv")
        wall, ok, task = {}, {}, {}
        for workers in (1, 2):
            with dask_client(workers=workers) as client:
                # warm-up on every worker: imports, compiled functions loaded from the cache
                client.run(calibrate_recording, load_template(template), str(tmp / "board00" / "data.csv"))
                t0 = time.perf_counter()
                s = run_batch(client, template, [pattern], lambda m: None)
                wall[workers] = time.perf_counter() - t0
                ok[workers] = sum(r.ok for r in s.results)
                task[workers] = sum(r.wall_s for r in s.results) / len(s.results)
    speedup = wall[1] / wall[2]
    load = os.getloadavg()[0]
    doc = {"boards": BOARDS, "wall_s": wall, "mean_task_s": task, "calibrated": ok, "speedup_2_over_1": speedup,
           "cores": os.cpu_count(),
           "load_average_1min_at_end": load}
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    (out / "batch_speedup.json").write_text(json.dumps(doc, indent=1) + "\n")
    md = (f"castimate batch, {BOARDS} simulated boards (8 triads x 20 poses, 100 Hz time series): 1 worker "
          f"{wall[1]:.1f} s, 2 workers {wall[2]:.1f} s, speed-up {speedup:.2f}; mean time per calibration on a worker "
          f"{task[1]:.2f} s and {task[2]:.2f} s ({os.cpu_count()} cores, 1-min load average {load:.1f} at the end; "
          f"{ok[1]} and {ok[2]} of {BOARDS} calibrated)")
    (out / "batch_speedup.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":  # Dask's worker processes import this file: run only as a script
    main()

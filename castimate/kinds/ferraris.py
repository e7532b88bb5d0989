"""The Ferraris protocol end to end: read the recording and imucal's section list, average the six
faces, integrate the turns, solve (castimate.problem.ferraris)."""

from __future__ import annotations

import numpy as np

from . import Log, quiet
from ..errors import InputError
from ..io.imucal import read_sections
from ..prepare.detect import Detection
from ..prepare.poses import average_poses
from ..problem.ferraris import FACES, TURNS, build_ferraris, turn_data
from ..spec import ProblemSpec
from .static import StaticData, StaticOutcome, declared_noise, gyro_sample_sigma, load_recording, solve_static, static_config


def ferraris_sections(spec: ProblemSpec, n_samples: int) -> dict[str, tuple[int, int]]:
    """The labelled sample ranges of the faces and turns, checked against the recording."""
    path = spec.data.sections
    sections = read_sections(path)
    for label in (*FACES, *TURNS):
        if label not in sections:
            raise InputError(path, label, f"missing section; the Ferraris protocol needs {', '.join((*FACES, *TURNS))}")
        if sections[label][1] > n_samples:
            raise InputError(path, f"{label}.end", f"expected at most {n_samples} (the recording's samples), "
                                                   f"found {sections[label][1]}")
    return sections


def calibrate_ferraris(spec: ProblemSpec, log: Log = quiet) -> StaticOutcome:
    """Accelerometer and gyroscope calibration of one IMU from the Ferraris protocol."""
    log(f"reading {spec.data.path.name} ({spec.data.format})")
    rec = load_recording(spec)
    name = spec.array.triads[0].name
    if name not in rec.gyro:
        raise InputError(spec.path, "array.triads[0]", f"the Ferraris turns need a gyroscope; {spec.data.path.name} has none")
    sec = ferraris_sections(spec, len(rec.t))
    faces = [sec[k] for k in FACES]
    det = Detection(faces, threshold_method=f"labelled faces from {spec.data.sections.name}",
                    segment_times=[(float(rec.t[a]), float(rec.t[b - 1])) for a, b in faces],
                    t_range=(float(rec.t[0]), float(rec.t[-1])), source=rec.source)
    avg = declared_noise(spec, average_poses(rec, det, triads=[name]))
    config, notes = static_config(spec, avg)
    turns = turn_data(rec.t, rec.gyro[name], [sec[k] for k in TURNS], np.array(list(TURNS.values())),
                      np.radians(spec.data.turn_angle_deg), gyro_sample_sigma(spec, avg)[name], config.triads[0].R_nominal)
    log(f"Ferraris protocol: 6 faces, 3 turns of {spec.data.turn_angle_deg:g} deg")
    problem = build_ferraris(config, avg, np.array(list(FACES.values()), float), turns)
    return solve_static(spec, StaticData(rec, avg, det), problem, notes, log, consistency=False)

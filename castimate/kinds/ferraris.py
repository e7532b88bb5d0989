"""The Ferraris protocol end to end: read the recording and imucal's section list, average the six
faces, integrate the turns, solve (castimate.problem.ferraris)."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from . import Log, quiet
from ..errors import InputError
from ..io.imucal import read_sections
from ..prepare.detect import Detection
from ..prepare.poses import average_poses
from ..problem.ferraris import FACES, TURNS, build_ferraris, turn_data
from ..problem.static import StaticConfig, StaticProblem
from ..spec import ProblemSpec
from ..prepare.plausibility import check_ferraris_sections
from .static import (StaticData, StaticKind, StaticOutcome, check_plausible, declared, declared_noise, load_recording,
                     session_config, solve_static)


@dataclass(frozen=True)
class FerrarisData(StaticData):
    """The six faces averaged (as static poses), and the turns' sample ranges."""

    turns: tuple[tuple[int, int], ...] = ()
    turn_angle: float = 0.0  # rad
    problem_path: object = ""


def ferraris_sections(spec: ProblemSpec, n_samples: int) -> dict[str, tuple[int, int]]:
    """The labelled sample ranges of the faces and turns, checked against the recording."""
    path = spec.data.sections
    sections = read_sections(path)
    labels = (*FACES, *TURNS)
    for label in sections:  # an unknown label was ignored: a misspelt or extra section, silently
        if label not in labels:
            raise InputError(path, label, f"unknown section; the Ferraris protocol's are {', '.join(labels)}")
    for label in labels:
        if label not in sections:
            raise InputError(path, label, f"missing section; the Ferraris protocol needs {', '.join(labels)}")
        if sections[label][1] > n_samples:
            raise InputError(path, f"{label}.end", f"expected at most {n_samples} (the recording's samples), "
                                                   f"found {sections[label][1]}")
    # overlapping sections were each averaged or integrated over the other's samples too, silently
    (a, (a0, a1)), (b, (b0, b1)) = min(pairwise(sorted(sections.items(), key=lambda kv: kv[1])),
                                       key=lambda p: p[1][1][0] - p[0][1][1])
    if b0 < a1:
        raise InputError(path, b, f"samples {b0} to {b1} overlap {a} ({a0} to {a1}; end exclusive); expected "
                                  "sections apart")
    return sections


def load_ferraris(spec: ProblemSpec, log: Log = quiet) -> FerrarisData:
    log(f"reading {spec.data.path.name} ({spec.data.format})")
    rec = load_recording(spec)
    name = spec.array.triads[0].name
    if name not in rec.gyro:
        raise InputError(spec.path, "array.triads[0]", f"the Ferraris turns need a gyroscope; {spec.data.path.name} has none")
    check_plausible(spec, rec, "static", log)
    sec = ferraris_sections(spec, len(rec.t))
    check_ferraris_sections(rec, name, sec, FACES, TURNS, spec.data.turn_angle_deg, spec.data.sections,
                            declared(spec))
    faces = [sec[k] for k in FACES]
    det = Detection(faces, threshold_method=f"labelled faces from {spec.data.sections.name}",
                    segment_times=[(float(rec.t[a]), float(rec.t[b - 1])) for a, b in faces],
                    t_range=(float(rec.t[0]), float(rec.t[-1])), source=rec.source)
    avg = declared_noise(spec, average_poses(rec, det, triads=[name]))
    given = spec.noise.gyroscope or {}
    sigma = {name: np.full(3, given[name]) if name in given else avg.gyro_sigma_sample[name]}
    log(f"Ferraris protocol: 6 faces, 3 turns of {spec.data.turn_angle_deg:g} deg")
    return FerrarisData(rec, avg, det, sigma, tuple(sec[k] for k in TURNS), float(np.radians(spec.data.turn_angle_deg)),
                        spec.path)


class FerrarisKind(StaticKind):
    """One IMU on six known faces and turned by a known angle about three axes (castimate.problem.ferraris)."""

    name = "ferraris"
    sampled = False
    warm_start = False

    def load(self, spec: ProblemSpec, log: Log = quiet) -> FerrarisData:
        return load_ferraris(spec, log)

    def configure(self, spec: ProblemSpec, data: FerrarisData, log: Log = quiet) -> StaticConfig:
        return session_config(spec, data)[0]

    def build(self, config: StaticConfig, data: FerrarisData, fixed_size: bool = False) -> StaticProblem:
        if fixed_size:
            raise InputError(data.problem_path, "kind", "C solvers are emitted for static_array and dynamic_array "
                                                        "problems, found ferraris")
        t = config.triads[0]
        turns = turn_data(data.recording.t, data.recording.gyro[t.name], list(data.turns), np.array(list(TURNS.values())),
                          data.turn_angle, data.gyro_sigma[t.name], t.R_nominal)
        return build_ferraris(config, data.averages, np.array(list(FACES.values()), float), turns)

    def calibrate(self, spec: ProblemSpec, data: FerrarisData, log: Log = quiet, quick: bool = False,
                  start: StaticOutcome | None = None) -> StaticOutcome:
        config, notes = session_config(spec, data)
        return solve_static(spec, data, self.build(config, data), notes, log, consistency=False)

    def window(self, spec: ProblemSpec, data, start: int, n: int):
        raise InputError(spec.path, "kind", "the Ferraris protocol needs all six faces and three turns; it has no window")

    def cross_validate(self, spec: ProblemSpec, data, folds: int, start=None, log: Log = quiet):
        raise InputError(spec.path, "kind", "diagnose tests the effect library on static_array and dynamic_array "
                                            "problems, found ferraris")


def calibrate_ferraris(spec: ProblemSpec, log: Log = quiet) -> StaticOutcome:
    """Accelerometer and gyroscope calibration of one IMU from the Ferraris protocol."""
    return KIND.calibrate(spec, KIND.load(spec, log), log)


KIND = FerrarisKind()

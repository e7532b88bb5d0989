"""Noise characterisation outputs: Kalibr's imu.yaml and a JSON document of the Allan deviations."""

from __future__ import annotations

from ..kinds.noise import NoiseOutcome
from ..prepare.allan import AllanResult

FORMAT = "castimate.noise/1"


def kalibr_imu_yaml(outcome: NoiseOutcome, triad: str) -> str:
    """Kalibr's IMU noise file for one triad (the largest of the three axes, continuous-time units).

    ``*_noise_density`` is N (m/s²/√Hz, rad/s/√Hz), ``*_random_walk`` is K (m/s³/√Hz, rad/s²/√Hz);
    a random walk the data are too short to resolve is written as its upper bound, with a comment.
    """
    acc, gyro = outcome.accelerometer[triad], outcome.gyroscope.get(triad)
    lines = [f"# IMU noise of triad {triad!r} from {outcome.spec.data.path.name}: Allan deviation of "
             f"{acc.duration:.0f} s of static data (castimate noise)",
             "rostopic: /imu0",
             f"update_rate: {acc.rate:.6g}  # Hz"]

    def entries(sensor: str, r: AllanResult, units: tuple[str, str]):
        bound = "" if all(t.random_walk_resolved for t in r.terms) else \
            f"  # upper bound: no +1/2 slope within {r.longest:.0f} s segments"
        return [f"{sensor}_noise_density: {r.axis_max('noise_density'):.6g}  # {units[0]}",
                f"{sensor}_random_walk: {r.axis_max('random_walk'):.6g}  # {units[1]}{bound}"]

    lines += entries("accelerometer", acc, ("m/s^2/sqrt(Hz)", "m/s^3/sqrt(Hz)"))
    if gyro is not None:
        lines += entries("gyroscope", gyro, ("rad/s/sqrt(Hz)", "rad/s^2/sqrt(Hz)"))
    else:
        lines.append("# no gyroscope in the data")
    return "\n".join(lines) + "\n"


def noise_document(outcome: NoiseOutcome) -> dict:
    """Every triad's Allan deviation curve and noise terms per axis."""
    def sensor(r: AllanResult) -> dict:
        return {"rate_hz": r.rate, "duration_s": r.duration, "longest_segment_s": r.longest,
                "tau_s": r.tau.tolist(), "adev": r.adev.tolist(),
                "axes": {ax: {"noise_density": t.noise_density, "bias_instability": t.bias_instability,
                              "random_walk": t.random_walk, "random_walk_resolved": t.random_walk_resolved,
                              "tau_min_deviation_s": t.tau_min_deviation}
                         for ax, t in zip("xyz", r.terms)}}

    return {"format": FORMAT, "problem": str(outcome.spec.path), "data": str(outcome.spec.data.path),
            "segments": [list(map(int, s)) for s in outcome.detection.segments],
            "units": {"accelerometer": "m/s^2", "gyroscope": "rad/s"},
            "triads": {n: {"accelerometer": sensor(outcome.accelerometer[n]),
                           **({"gyroscope": sensor(outcome.gyroscope[n])} if n in outcome.gyroscope else {})}
                       for n in outcome.accelerometer}}

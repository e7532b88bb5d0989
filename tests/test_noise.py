"""Noise characterisation: the overlapping Allan variance by hand, known densities recovered within
their sampling error, Kalibr's imu.yaml from the CLI."""

import numpy as np
import pytest
import yaml

from castimate.cli import main
from castimate.errors import InputError
from castimate.prepare.allan import allan_deviation, allan_variance


def test_allan_variance_by_hand():
    # theta = [0, 1, 4, 6, 12]; second differences 2, -1, 4: AVAR(1) = 21 / (2 * 1 * 3) = 3.5
    # (= half the mean squared first difference of x: (4 + 1 + 16) / 6)
    avar, cnt = allan_variance([np.array([1.0, 3, 2, 6])], 1.0, np.array([1, 2]))
    assert avar[0, 0] == pytest.approx(3.5) and cnt[0] == 3
    # m = 2: theta_4 - 2 theta_2 + theta_0 = 12 - 8 = 4: 16 / (2 * 4 * 1) = 2
    assert avar[1, 0] == pytest.approx(2.0) and cnt[1] == 1
    # two segments pool their terms; a segment too short for m adds nothing
    avar2, cnt2 = allan_variance([np.array([1.0, 3, 2, 6]), np.array([0.0, 1.0])], 1.0, np.array([1, 2]))
    assert cnt2.tolist() == [4, 1] and avar2[0, 0] == pytest.approx((21 / 2 + 1 / 2) / 4)


def test_white_noise_density():
    """σ_d = 0.01 per sample at 100 Hz is N = σ_d / sqrt(100) = 1e-3 /sqrt(Hz). The estimate's
    relative σ over 20 000 samples is 1.75 % (Monte Carlo, 60 axes); allow 3.5 σ."""
    rng = np.random.default_rng(3)
    r = allan_deviation([0.01 * rng.standard_normal((20000, 3))], 0.01)
    for t in r.terms:
        assert t.noise_density == pytest.approx(1e-3, rel=0.06)
        assert not t.random_walk_resolved  # white noise only: K is a bound
    assert r.rate == pytest.approx(100.0) and r.duration == pytest.approx(200.0)


def test_rate_random_walk():
    """White noise plus a random walk of K = 1e-3 /s/sqrt(Hz) over 2000 s: K within 25 % (the
    long-τ AVAR rests on a few tens of independent differences), N still within 3 %."""
    rng = np.random.default_rng(0)
    dt, n = 0.01, 200_000
    x = 0.01 * rng.standard_normal((n, 3)) + np.cumsum(1e-3 * np.sqrt(dt) * rng.standard_normal((n, 3)), axis=0)
    for t in allan_deviation([x], dt).terms:
        assert t.random_walk_resolved and t.random_walk == pytest.approx(1e-3, rel=0.25)
        assert t.noise_density == pytest.approx(1e-3, rel=0.03)


def _static_session(tmp_path, rows=False):
    from castimate.io.readers import write_npz
    from castimate.simulate.static import pose_directions, random_static_truth, static_time_series

    rng = np.random.default_rng(4)
    truth = random_static_truth(["imu"], "imu", rng, gyroscope=True)
    rec, _ = static_time_series(truth, pose_directions(8, rng), 0.02, rng, pose_duration=6.0, transition=1.5,
                                gyro_sigma=0.003)
    write_npz(tmp_path / "data.npz", rec)
    p = tmp_path / "problem.yaml"
    p.write_text("kind: static_array\ndata: {path: data.npz, format: npz}\n"
                 "array: {reference: imu, triads: [{name: imu}]}\n")
    return p


def test_noise_cli_writes_kalibr_yaml(tmp_path):
    p = _static_session(tmp_path)
    assert main(["noise", str(p), "-o", str(tmp_path / "out"), "-q"]) == 0
    imu = yaml.safe_load((tmp_path / "out" / "imu.yaml").read_text())
    assert imu["update_rate"] == pytest.approx(100.0)
    # simulated white noise 0.02 and 0.003 per sample at 100 Hz: densities 2e-3 and 3e-4 per sqrt(Hz)
    assert imu["accelerometer_noise_density"] == pytest.approx(2e-3, rel=0.15)
    assert imu["gyroscope_noise_density"] == pytest.approx(3e-4, rel=0.15)
    assert {"accelerometer_random_walk", "gyroscope_random_walk"} <= set(imu)
    assert (tmp_path / "out" / "allan.png").stat().st_size > 1000


def test_noise_refuses_rows(tmp_path):
    from castimate.kinds.noise import characterise_noise
    from castimate.spec import load_problem

    p = tmp_path / "problem.yaml"
    (tmp_path / "data.csv").write_text("t,imu.ax,imu.ay,imu.az\n0,0,0,9.81\n1,0,9.81,0\n")
    p.write_text("kind: static_array\ndata: {path: data.csv, format: csv, segments: rows}\n"
                 "array: {reference: imu, triads: [{name: imu}]}\nnoise: {accelerometer: 0.01}\n")
    with pytest.raises(InputError, match="data.segments.*raw time series"):
        characterise_noise(load_problem(p))

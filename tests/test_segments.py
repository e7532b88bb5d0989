"""Tests of castimate.segments: static-pose detection and pose averaging."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from castimate.errors import InputError
from castimate.io.recording import Recording
from castimate.prepare.detect import Detection, detect_static, explicit_segments
from castimate.prepare.options import DetectionOptions
from castimate.prepare.poses import PoseAverages, average_poses, pose_averages_from_means

G = 9.81
DATA = Path(__file__).parents[2] / "shared" / "data"


# ------------------------------------------------------------------------------------------
# Synthetic sessions
# ------------------------------------------------------------------------------------------

def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


class _Session:
    """Builds the specific force (body frame) of a sequence of rests and motions."""

    def __init__(self, u0, fs: float = 100.0):
        self.fs = fs
        self.u = _unit(u0)
        self.f: list[np.ndarray] = []
        self.n = 0
        self.truth: list[tuple[int, int]] = []   # true static sample ranges

    def _add(self, f: np.ndarray) -> tuple[int, int]:
        self.f.append(f)
        a = self.n
        self.n += len(f)
        return a, self.n

    def static(self, dur: float, record: bool = True):
        n = int(round(dur * self.fs))
        rng = self._add(np.tile(G * self.u, (n, 1)))
        if record:
            self.truth.append(rng)
        return rng

    def move(self, u1, dur: float, smooth: bool = True):
        """Rotate the gravity direction to u1 (about u x u1); smooth = zero rate at both ends."""
        u1 = _unit(u1)
        n = int(round(dur * self.fs))
        axis = np.cross(self.u, u1)
        angle = math.atan2(np.linalg.norm(axis), float(self.u @ u1))
        tau = (np.arange(n) + 1) / n
        prof = tau - np.sin(2 * np.pi * tau) / (2 * np.pi) if smooth else tau
        f = np.array([G * _rotation(axis, angle * p) @ self.u for p in prof])
        self.u = u1
        return self._add(f)

    def bump(self, dur: float, amp: float):
        """A tap: the orientation is kept, a short oscillation is added."""
        n = int(round(dur * self.fs))
        k = np.arange(n) / self.fs
        osc = amp * np.sin(2 * np.pi * 8 * k)[:, None] * np.array([0.6, 0.5, 0.62])
        return self._add(G * self.u + osc)

    def recording(self, noise: float, rng: np.random.Generator, n_triads: int = 3) -> Recording:
        f = np.concatenate(self.f)
        t = np.arange(len(f)) / self.fs
        acc = {}
        for j in range(n_triads):
            R = _rotation(rng.normal(size=3), rng.uniform(0, np.pi))
            b = rng.normal(scale=0.1, size=3)
            acc[f"imu{j + 1}"] = f @ R.T + b + noise * rng.normal(size=f.shape)
        return Recording(t=t, acc=acc, source="synthetic")


def _random_directions(rng: np.random.Generator, n: int, min_angle_deg: float = 30.0) -> list[np.ndarray]:
    dirs = [_unit(rng.normal(size=3))]
    while len(dirs) < n:
        u = _unit(rng.normal(size=3))
        if math.degrees(math.acos(np.clip(u @ dirs[-1], -1, 1))) >= min_angle_deg:
            dirs.append(u)
    return dirs


def _twelve_poses(seed: int = 7) -> _Session:
    rng = np.random.default_rng(seed)
    dirs = _random_directions(rng, 12)
    s = _Session(dirs[0])
    for k in range(12):
        if k:
            s.move(dirs[k], rng.uniform(2.0, 3.0))
        s.static(rng.uniform(4.0, 15.0))
    return s


@pytest.mark.parametrize("noise", [0.002, 0.02, 0.2])
def test_twelve_poses_found_with_adaptive_threshold(noise):
    """The same default options find all 12 poses whatever the noise level (10x either way)."""
    session = _twelve_poses()
    rec = session.recording(noise, np.random.default_rng(11))
    opts = DetectionOptions()
    det = detect_static(rec, opts)

    assert isinstance(det, Detection)
    assert det.n_poses == 12, det.summary()
    assert det.rejected == [], det.summary()   # no false candidates at all
    assert det.threshold_method.startswith("specific force: adaptive")
    # the adaptive threshold follows the noise (2 x floor, floor ~ noise)
    assert 1.5 * noise < det.threshold < 2.5 * noise
    t = rec.t
    for (a, b), (ta, tb) in zip(det.segments, session.truth):
        t0, t1 = t[a], t[b - 1]
        true0, true1 = t[ta], t[tb - 1]
        # within the trim (at most 0.5 s) and one window of the true edges
        assert abs(t0 - true0) <= 0.5 + det.window, det.summary()
        assert abs(t1 - true1) <= 0.5 + det.window, det.summary()
        # no motion inside an accepted segment: at most the first 0.15 s of a turn, in which
        # the smooth profile moves gravity by < 0.1 m/s² (undetectable under 0.2 m/s² noise)
        assert t0 >= true0 - 0.15 and t1 <= true1 + 0.15, det.summary()
    text = det.summary()
    assert "12 poses accepted" in text and "pose  12" in text


def test_triads_of_very_different_noise_combine():
    """Each channel is normalised by its own floor: a 100x noisier triad does not blind the others."""
    session = _twelve_poses(seed=21)
    rng = np.random.default_rng(4)
    recs = [session.recording(noise, rng, n_triads=1) for noise in (0.002, 0.02, 0.2)]
    rec = Recording(t=recs[0].t, acc={f"imu{j + 1}": r.acc["imu1"] for j, r in enumerate(recs)})
    det = detect_static(rec)
    assert det.n_poses == 12 and det.rejected == [], det.summary()
    for (a, b), (ta, tb) in zip(det.segments, session.truth):
        assert ta - 15 <= a and b <= tb + 15


def test_short_and_drifting_rests_are_rejected_with_reasons():
    rng = np.random.default_rng(3)
    d = _random_directions(rng, 5, 40.0)
    s = _Session(d[0])
    s.static(8.0)
    s.move(d[1], 2.5)
    short = s.static(0.6, record=False)  # shorter than two 0.5 s windows
    s.move(d[2], 2.5)
    s.static(8.0)
    s.move(d[3], 2.5)
    # slow tilt: 5 degrees in 10 s, too slow for the windowed statistic, caught by the drift test
    tilt = _unit(_rotation(np.cross(d[3], d[4]), math.radians(5.0)) @ d[3])
    drift = s.move(tilt, 10.0, smooth=False)
    s.move(d[4], 2.5)
    s.static(8.0)
    rec = s.recording(0.02, rng)
    det = detect_static(rec)

    assert det.n_poses == 3, det.summary()
    assert all(b <= drift[0] or a >= drift[1] for a, b in det.segments), det.summary()  # no pose in the tilt
    rejected = sorted(det.rejected)
    assert len(rejected) == 2 and all(r[2].startswith("too short") for r in rejected), det.summary()
    a, b, why = rejected[0]
    assert a <= short[0] + 50 and b >= short[1] - 50
    assert "< 1 s" in why
    # the slow tilt: its edges refined away until what is left is too short (the mean-shift test sees
    # the ramp that the windowed standard deviation does not)
    a, b, why = rejected[1]
    assert drift[0] <= a and b <= drift[1], det.summary()
    assert "too short" in det.summary()

    # the edge refinement alone keeps it out, drift test or not
    assert detect_static(rec, DetectionOptions(max_drift=None)).n_poses == 3
    # a longer minimum rejects everything shorter than 9 s
    det3 = detect_static(rec, DetectionOptions(min_duration=9.0))
    assert det3.n_poses == 0 and len(det3.rejected) == 5


def test_a_pose_that_shifts_in_its_middle_is_drifting():
    """A 2° nudge (0.34 m/s²) in the middle of a 16 s rest: the two halves are merged (same orientation
    within 5°), their edges match the mixed middle, and the drift test rejects the segment; without the
    drift test it is one pose."""
    rng = np.random.default_rng(8)
    d = _random_directions(rng, 2, 40.0)
    s = _Session(d[0])
    s.static(8.0)
    s.move(_unit(_rotation(np.cross(d[0], d[1]), math.radians(2.0)) @ d[0]), 0.3)
    s.static(8.0)
    rec = s.recording(0.02, rng)
    det = detect_static(rec)
    assert det.n_poses == 0, det.summary()
    why = [r[2] for r in det.rejected if not r[2].startswith("merged")]
    assert len(why) == 1 and why[0].startswith("drifting (mean changes by 0.3") and "between halves" in why[0], why
    assert detect_static(rec, DetectionOptions(max_drift=None)).n_poses == 1


def test_tap_is_merged_and_returning_pose_is_noted():
    rng = np.random.default_rng(5)
    d = _random_directions(rng, 3, 40.0)
    s = _Session(d[0])
    s.static(6.0)
    s.bump(0.4, 1.5)          # a tap: same orientation after it
    s.static(6.0)
    s.move(d[1], 2.5)
    s.static(8.0)
    s.move(d[0], 2.5)          # back to the first orientation
    s.static(8.0)
    rec = s.recording(0.02, rng)
    det = detect_static(rec)

    assert det.n_poses == 3, det.summary()
    merged = [r for r in det.rejected if r[2].startswith("merged with previous")]
    assert len(merged) == 1 and len(det.rejected) == 1, det.summary()
    assert "same orientation" in merged[0][2]
    a, b = det.segments[0]
    assert rec.t[a] < 1.0 and rec.t[b - 1] > 11.5          # spans the tap
    notes = dict(det.notes)
    assert "repeated orientation (same as pose 1" in notes[2]
    assert "repeated orientation" in det.summary()

    # without merging the two halves are separate poses, the second noted as repeated
    det2 = detect_static(rec, DetectionOptions(merge_gap=0.0))
    assert det2.n_poses == 4
    assert "repeated orientation (same as pose 1" in dict(det2.notes)[1]


def test_given_threshold_overrides_adaptive():
    rec = _twelve_poses().recording(0.02, np.random.default_rng(1))
    det = detect_static(rec, DetectionOptions(threshold=0.08))
    assert det.threshold == 0.08
    assert det.threshold_method.startswith("specific force: given")
    assert det.n_poses == 12
    # a threshold below the noise finds nothing static
    det = detect_static(rec, DetectionOptions(threshold=0.005))
    assert det.n_poses == 0


def test_detection_with_gyroscopes():
    session = _twelve_poses()
    rng = np.random.default_rng(2)
    rec = session.recording(0.02, rng)
    f = np.concatenate(session.f)
    # angular rate magnitude from the rotation of the gravity direction (body frame)
    u = f / np.linalg.norm(f, axis=1, keepdims=True)
    rate = np.cross(u[:-1], u[1:]) * 100.0
    rate = np.vstack([rate, rate[-1:]])
    gyro = {k: rate + 0.01 + 0.003 * rng.normal(size=rate.shape) for k in rec.acc}
    rec = Recording(t=rec.t, acc=rec.acc, gyro=gyro, source="synthetic")
    det = detect_static(rec)
    assert det.n_poses == 12 and det.gyro_threshold is not None
    assert 1.5 * 0.003 < det.gyro_threshold < 2.5 * 0.003
    det = detect_static(rec, DetectionOptions(max_gyro=0.002))
    assert det.n_poses == 12                       # bias removed: at rest the rate is zero
    assert det.gyro_statistic is not None and det.gyro_statistic.shape == rec.t.shape


# ------------------------------------------------------------------------------------------
# Pose averaging
# ------------------------------------------------------------------------------------------

def _white_recording(sigma, n_seg: int, seg_len: int, rng, ar: float = 0.0, n_triads: int = 3):
    """Static segments of length seg_len with AR(1) noise of innovation σ (white if ar = 0)."""
    P = n_seg
    N = P * seg_len
    acc = {}
    truth_means = {}
    for j in range(n_triads):
        levels = rng.normal(scale=5.0, size=(P, 3))
        e = rng.normal(size=(N, 3)) * sigma
        if ar:
            x = np.empty_like(e)
            x[0] = e[0] / math.sqrt(1 - ar * ar)
            for i in range(1, N):
                x[i] = ar * x[i - 1] + e[i]
            e = x
        acc[f"imu{j + 1}"] = np.repeat(levels, seg_len, axis=0) + e
        truth_means[f"imu{j + 1}"] = levels
    t = np.arange(N) / 100.0
    segs = [(k * seg_len, (k + 1) * seg_len) for k in range(P)]
    return Recording(t=t, acc=acc, gyro={"imu1": acc["imu1"] * 0.01}, source="white"), segs


def test_average_poses_means_and_white_noise_sigma():
    rng = np.random.default_rng(42)
    sigma = np.array([0.02, 0.05, 0.01])
    rec, segs = _white_recording(sigma, n_seg=12, seg_len=1003, rng=rng)
    det = Detection(segments=segs)
    pa = average_poses(rec, det)
    assert isinstance(pa, PoseAverages)
    assert pa.n_poses == 12 and pa.triads == ("imu1", "imu2", "imu3")
    np.testing.assert_array_equal(pa.n, np.full(12, 1003))
    np.testing.assert_allclose(pa.t_start, [rec.t[a] for a, _ in segs])
    for k in rec.acc:
        hand = np.array([rec.acc[k][a:b].mean(axis=0) for a, b in segs])
        np.testing.assert_allclose(pa.acc_mean[k], hand, rtol=0, atol=1e-12)
        assert pa.acc_mean[k].shape == (12, 3) and pa.acc_sigma[k].shape == (12, 3)
    np.testing.assert_allclose(pa.gyro_mean["imu1"], 0.01 * pa.acc_mean["imu1"], atol=1e-12)
    assert set(pa.gyro_mean) == {"imu1"}

    # pooled batch means: σ̂²/σ² ~ χ²_dof / dof with dof = 12 segments x (8 blocks - 1)
    dof = 12 * (8 - 1)
    assert pa.sigma_dof == dof
    lo, hi = chi2.ppf(1e-4, dof) / dof, chi2.ppf(1 - 1e-4, dof) / dof
    for k in rec.acc:
        ratio = (pa.acc_sigma_sample[k] / sigma) ** 2
        assert np.all((lo < ratio) & (ratio < hi)), (k, ratio, lo, hi)
        np.testing.assert_allclose(pa.acc_sigma[k], np.tile(pa.acc_sigma_sample[k] / math.sqrt(1003), (12, 1)))
    # over all 9 channels the mean ratio is tighter still: χ²_{9 dof}/(9 dof)
    allr = np.concatenate([(pa.acc_sigma_sample[k] / sigma) ** 2 for k in rec.acc])
    assert chi2.ppf(1e-4, 9 * dof) / (9 * dof) < allr.mean() < chi2.ppf(1 - 1e-4, 9 * dof) / (9 * dof)


def test_batch_means_capture_correlated_noise():
    """AR(1) noise: the white-noise-equivalent σ is σ_e/(1-φ), not the sample standard deviation."""
    rng = np.random.default_rng(8)
    phi, sig_e = 0.5, 0.02
    rec, segs = _white_recording(np.full(3, sig_e), n_seg=12, seg_len=2000, rng=rng, ar=phi, n_triads=1)
    pa = average_poses(rec, Detection(segments=segs))
    expected = sig_e / (1 - phi)                    # sqrt of the spectral density at 0
    dof = pa.sigma_dof
    # batch-means bias for AR(1) with block length L: about 2φ/((1-φ²)L) relative; allow 3 %
    lo, hi = chi2.ppf(1e-4, dof) / dof * 0.97, chi2.ppf(1 - 1e-4, dof) / dof
    ratio = (pa.acc_sigma_sample["imu1"] / expected) ** 2
    assert np.all((lo < ratio) & (ratio < hi)), ratio
    sample_std = sig_e / math.sqrt(1 - phi ** 2)
    assert np.all(pa.acc_sigma_sample["imu1"] > 1.4 * sample_std)


def test_outlier_segment_does_not_inflate_sigma():
    rng = np.random.default_rng(9)
    rec, segs = _white_recording(np.full(3, 0.02), n_seg=12, seg_len=800, rng=rng, n_triads=1)
    acc = rec.acc["imu1"].copy()
    acc[segs[4][0] + 100: segs[4][0] + 140] += 1.0   # a tap inside one segment
    rec = Recording(t=rec.t, acc={"imu1": acc})
    pa = average_poses(rec, Detection(segments=segs))
    assert np.all(pa.acc_sigma_sample["imu1"] < 0.025)


def test_pose_averages_from_means():
    means = {"a": np.ones((4, 3)), "b": np.zeros((4, 3))}
    pa = pose_averages_from_means(means, n=[100, 400, 100, 100], acc_sigma_sample={"a": 0.02, "b": [0.01, 0.02, 0.03]},
                                  gyro_mean={"a": np.zeros((4, 3))}, gyro_sigma_sample=0.001)
    assert pa.n_poses == 4 and pa.sigma_dof == 0
    np.testing.assert_allclose(pa.acc_sigma["a"][1], [0.001] * 3)
    np.testing.assert_allclose(pa.acc_sigma["b"][0], [0.001, 0.002, 0.003])
    np.testing.assert_allclose(pa.gyro_sigma["a"][0], [1e-4] * 3)
    assert np.all(np.isnan(pa.t_start))
    with pytest.raises(InputError, match=r"acc_mean\.b.*expected 4 poses"):
        pose_averages_from_means({"a": np.ones((4, 3)), "b": np.ones((3, 3))}, 10, 0.01, where="poses")
    with pytest.raises(InputError, match=r"acc_mean\.a.*shape \(P, 3\)"):
        pose_averages_from_means({"a": np.ones((4, 2))}, 10, 0.01)
    with pytest.raises(InputError, match=r"\bn\b.*shape \(4,\)"):
        pose_averages_from_means({"a": np.ones((4, 3))}, [10, 10], 0.01)
    with pytest.raises(InputError, match=r"acc_sigma_sample\.c.*unknown triad"):
        pose_averages_from_means({"a": np.ones((4, 3))}, 10, {"a": 0.01, "c": 0.01})
    with pytest.raises(InputError, match=r"acc_sigma_sample\.a.*positive"):
        pose_averages_from_means({"a": np.ones((4, 3))}, 10, -0.01)
    with pytest.raises(InputError, match="gyro_sigma_sample"):
        pose_averages_from_means({"a": np.ones((4, 3))}, 10, 0.01, gyro_mean={"a": np.ones((4, 3))})


# ------------------------------------------------------------------------------------------
# Explicit segments and input errors
# ------------------------------------------------------------------------------------------

def _plain_recording(seconds: float = 20.0, fs: float = 100.0) -> Recording:
    n = int(seconds * fs)
    rng = np.random.default_rng(0)
    return Recording(t=np.arange(n) / fs, acc={"imu1": rng.normal(size=(n, 3))}, source="rec.csv")


def test_explicit_segments():
    rec = _plain_recording()
    det = explicit_segments(rec, [[1.0, 2.0], [5, 9.5], [3.0, 4.0]], "p.yaml", "data.segments")
    assert det.segments == [(100, 201), (500, 951), (300, 401)]   # t0 <= t <= t1, given order
    assert det.rejected == [] and det.threshold is None
    assert "explicit" in det.threshold_method
    assert "3 poses accepted" in det.summary()
    pa = average_poses(rec, det)
    np.testing.assert_allclose(pa.acc_mean["imu1"][1], rec.acc["imu1"][500:951].mean(axis=0))
    # whole recording
    det = explicit_segments(rec, [[0.0, 19.99]], "p.yaml", "data.segments")
    assert det.segments == [(0, 2000)]


@pytest.mark.parametrize("segments, where, message", [
    ([[1.0, 2.0], [15.0, 25.0]], r"data\.segments\[1\]", "outside the recording"),
    ([[-1.0, 2.0]], r"data\.segments\[0\]", "outside the recording"),
    ([[1.0, 2.0], [4.0, 3.0]], r"data\.segments\[1\]", "t0 < t1"),
    ([[3.0, 3.0]], r"data\.segments\[0\]", "t0 < t1"),
    ([[1.0, 5.0], [6.0, 8.0], [4.0, 7.0]], r"data\.segments\[2\]", r"overlaps data\.segments\[0\]"),
    ([[1.0, 1.05]], r"data\.segments\[0\]", "at least 10"),
    ([[1.0, 2.0], [3.0]], r"data\.segments\[1\]", r"pair \[t0, t1\]"),
    ([[1.0, "x"]], r"data\.segments\[0\]\[1\]", "expected a finite number"),
    ([], r"data\.segments", "at least one"),
    ("1-2", r"data\.segments", "list of"),
])
def test_explicit_segment_errors(segments, where, message):
    rec = _plain_recording()
    with pytest.raises(InputError, match=where + ".*" + message) as e:
        explicit_segments(rec, segments, "p.yaml", "data.segments")
    assert e.value.source == "p.yaml"


def test_options_from_mapping():
    o = DetectionOptions.from_mapping({"window": 2, "threshold": 0.05, "max_gyro": "auto",
                                       "use_gyro": False}, "p.yaml", "data.detection")
    assert o.window == 2.0 and isinstance(o.window, float)
    assert o.threshold == 0.05 and o.max_gyro is None and o.use_gyro is False
    assert o.min_duration == DetectionOptions().min_duration
    assert DetectionOptions.from_mapping(None) == DetectionOptions()
    assert DetectionOptions.from_mapping({"threshold": None}).threshold is None


@pytest.mark.parametrize("mapping, where, message", [
    ({"windw": 1.0}, r"data\.detection\.windw", "unknown key.*window"),
    ({"window": -1.0}, r"data\.detection\.window", "expected a positive finite number, found -1.0"),
    ({"window": True}, r"data\.detection\.window", "expected a positive finite number, found True"),
    ({"window": 1e300}, r"data\.detection\.window", "expected a number at most 600 s"),
    ({"threshold": "high"}, r"data\.detection\.threshold", "expected a positive finite number"),
    ({"threshold_factor": 0.5}, r"data\.detection\.threshold_factor", "expected a number from 1 to 1000"),
    ({"floor_quantile": 0.9}, r"data\.detection\.floor_quantile", "expected a number at most 0.5"),
    ({"use_gyro": "yes"}, r"data\.detection\.use_gyro", "true or false"),
    ({"min_separation_deg": float("nan")}, r"data\.detection\.min_separation_deg", "finite"),
    ([1, 2], r"data\.detection", "mapping"),
])
def test_options_errors(mapping, where, message):
    with pytest.raises(InputError, match=where + ".*" + message) as e:
        DetectionOptions.from_mapping(mapping, "p.yaml", "data.detection")
    assert e.value.source == "p.yaml"


def test_other_input_errors():
    rec = _plain_recording()
    with pytest.raises(InputError, match="DetectionOptions: trim"):
        DetectionOptions(trim=-1.0)
    with pytest.raises(InputError, match="triad 'imu9' is not in the recording"):
        detect_static(rec, triads=["imu9"])
    with pytest.raises(InputError, match="triad 'imu9' is not in the recording"):
        average_poses(rec, Detection(segments=[(0, 100)]), triads=["imu9"])
    with pytest.raises(InputError, match="too few"):
        detect_static(Recording(t=np.arange(20) / 100, acc={"a": np.zeros((20, 3))}))
    with pytest.raises(InputError, match="outside the recording"):
        average_poses(rec, Detection(segments=[(1900, 2100)]))


# ------------------------------------------------------------------------------------------
# Real data
# ------------------------------------------------------------------------------------------

def _read_mimu(path: Path) -> Recording:
    from castimate.io.mimu import read_mimu

    return read_mimu(path)


def _static_phase(rec: Recording) -> Recording:
    return rec.select(rec.t - rec.t[0] < 495.0)


def _angles_deg(dirs: np.ndarray) -> np.ndarray:
    u = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(u @ u.T, -1, 1)))


@pytest.mark.parametrize("session", [1, 2, 3, 4, 5])
def test_mimu4444_static_phase(session):
    path = DATA / "mimu4444" / f"exp_{session}" / "data.bin"
    assert path.is_file(), f"shared data missing: {path}"
    rec = _static_phase(_read_mimu(path))
    det = detect_static(rec)
    assert det.n_poses == 20, det.summary()
    assert det.gyro_threshold is not None
    durations = [t1 - t0 for t0, t1 in det.segment_times]
    # ~23 s each; the last pose is cut by the 495 s limit
    assert all(18.0 < d < 35.0 for d in durations[:-1]), det.summary()
    assert 3.0 < durations[-1] < 35.0
    pa = average_poses(rec, det)
    first = rec.triads[0]
    # icosahedron faces: normals at least ~41.8 degrees apart
    ang = _angles_deg(pa.acc_mean[first])
    assert ang[~np.eye(20, dtype=bool)].min() > 30.0
    norms = np.linalg.norm(pa.acc_mean[first], axis=1)
    assert np.all((9.0 < norms) & (norms < 10.6))
    if session == 1:
        s = pa.acc_sigma_sample[first]
        assert np.all((0.02 < s) & (s < 0.08)), s           # MPU9150 at ±16 g: ~0.04 m/s²
        g = pa.gyro_sigma_sample[first]
        assert np.all((5e-4 < g) & (g < 0.02)), g


def _read_xsens() -> Recording:
    folder = DATA / "imu_tk_xsens"
    assert folder.is_dir(), f"shared data missing: {folder}"
    a = np.loadtxt(folder / "xsens_acc.mat")
    g = np.loadtxt(folder / "xsens_gyro.mat")
    acc = (a[:, 1:] - [33123, 33276, 32360]) / [415, 413, 415]
    gyro = (g[:, 1:] - [32768, 32466, 32485]) / [4778, 4758, 4766]
    return Recording(t=a[:, 0], acc={"xsens": acc}, gyro={"xsens": gyro}, source=str(folder))


def test_imu_tk_xsens_session():
    rec = _read_xsens()
    det = detect_static(rec)
    print(det.summary())
    # about 37 poses plus the initial ~50 s rest
    assert 35 <= det.n_poses <= 40, det.summary()
    t0, t1 = det.segment_times[0]
    assert t0 < 1.0 and 45.0 < t1 - t0 < 55.0
    assert all(t1 - t0 >= 2.0 for t0, t1 in det.segment_times)
    pa = average_poses(rec, det)
    ang = _angles_deg(pa.acc_mean["xsens"])
    # consecutive poses are distinct orientations ...
    assert np.all(np.diag(ang, 1) > DetectionOptions().min_separation_deg)
    # ... and the session visits many distinct directions (some are revisited; those are noted)
    clusters: list[int] = []
    for i in range(len(ang)):
        if all(ang[i, j] > 10.0 for j in clusters):
            clusters.append(i)
    assert len(clusters) >= 10
    repeated = [i for i, text in det.notes if text.startswith("repeated orientation")]
    assert len(repeated) == det.n_poses - len([i for i in range(len(ang))
                                                if all(ang[i, j] >= 5.0 for j in range(i))])
    norms = np.linalg.norm(pa.acc_mean["xsens"], axis=1)
    assert np.all(np.abs(norms - 9.81) < 0.3)

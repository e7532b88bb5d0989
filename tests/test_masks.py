"""Saturation masks: both rails of an ADC, each found on its own (issue 11 item 1)."""

import math

import numpy as np
import pytest

from castimate.errors import InputError
from castimate.io.mimu import INT16_RAILS
from castimate.io.recording import Recording
from castimate.io.units import UnitConversion, declared_rails, parse_units
from castimate.prepare.masks import SaturationOptions, plateau_rails, saturation_mask

#: MPU9150 gyroscope at ±2000 °/s: 16.4 counts per °/s, in rad/s per count.
GYRO_SCALE = math.radians(1 / 16.4)


def int16_gyro(true_rad_s: np.ndarray) -> np.ndarray:
    """What an int16 ADC reports for angular rates (rad/s): rounded to counts, clipped at −32768 and +32767."""
    counts = np.clip(np.round(true_rad_s / GYRO_SCALE), -32768, 32767)
    return counts * GYRO_SCALE


def twisting_rate(n: int = 2000, seed: int = 3) -> np.ndarray:
    """Angular rates (rad/s) of a hand twist that overshoots both rails (±1998 °/s) on every axis."""
    t = np.arange(n) / 62.5
    phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, 3)
    return np.radians(2300) * np.sin(2 * np.pi * 1.7 * t[:, None] + phase)


def test_int16_rails_are_asymmetric_and_both_are_masked():
    true = twisting_rate()
    y = int16_gyro(true)
    lo, hi = -32768 * GYRO_SCALE, 32767 * GYRO_SCALE
    clipped_low, clipped_high = (true < lo).any(axis=1), (true > hi).any(axis=1)
    assert clipped_low.sum() > 100 and clipped_high.sum() > 100  # both rails are hit
    rails = np.array([[lo] * 3, [hi] * 3])
    for m in (saturation_mask(y, "auto", rails), saturation_mask(y, "auto")):  # from the ADC; as plateaus
        # The one-rail mask (samples at the largest |y| only) leaves the +32767 samples in: this fails on it.
        assert m.masked.tolist() == (clipped_low | clipped_high).tolist()
        assert m.low.any(axis=1).tolist() == clipped_low.tolist() and m.high.any(axis=1).tolist() == clipped_high.tolist()
        # each axis on its own: the unclipped axes of a clipped sample still count
        assert m.axes.tolist() == ((true < lo) | (true > hi)).tolist()
        assert m.counts() == {"low": clipped_low.sum(), "high": clipped_high.sum(), "adjacent": 0,
                              "masked": (clipped_low | clipped_high).sum(), "axes": ((true < lo) | (true > hi)).sum()}
        np.testing.assert_allclose(m.rails, rails, rtol=1e-12)
    assert saturation_mask(y, "auto", rails).source == "adc" and saturation_mask(y, "auto").source == "plateau"


def test_hand_computed_margin_and_adjacent_samples():
    # One axis, rails at -4 and +5 (full range 9); the other axes quiet.
    y = np.zeros((10, 3))
    y[:, 0] = [0, 4.9, 5, 5, 1, -3.9, -4, 2, 4.6, 0]
    rails = np.array([[-4, -4, -4], [5, 5, 5]], float)
    m = saturation_mask(y, "auto", rails)
    assert np.flatnonzero(m.masked).tolist() == [2, 3, 6]  # exactly on a rail
    assert (m.counts()["low"], m.counts()["high"]) == (1, 2)
    # margin 0.05 of the range 9 = 0.45: 4.9 >= 5 - 0.45 and 4.6 >= 4.55 join the high rail; -3.9 <= -3.55 the low
    m = saturation_mask(y, "auto", rails, margin=0.05)
    assert np.flatnonzero(m.high[:, 0]).tolist() == [1, 2, 3, 8] and np.flatnonzero(m.low[:, 0]).tolist() == [5, 6]
    assert not m.axes[:, 1:].any()
    # one sample on each side of every run on a rail (runs 2-3 and 6): 1, 4, 5, 7 join
    m = saturation_mask(y, "auto", rails, adjacent=1)
    assert np.flatnonzero(m.masked).tolist() == [1, 2, 3, 4, 5, 6, 7]
    assert m.counts() == {"low": 1, "high": 2, "adjacent": 4, "masked": 7, "axes": 7}
    # a declared level: |y| >= 4.6 -> 4.9, 5, 5, 4.6 (high), none low
    m = saturation_mask(y, 4.6)
    assert np.flatnonzero(m.masked).tolist() == [1, 2, 3, 8] and m.counts()["low"] == 0
    assert not saturation_mask(y, "none").masked.any()


def test_plateaus_are_found_at_each_extreme_separately():
    y = np.zeros((12, 3))
    y[:, 0] = [1, 7, 7, 7, 2, -6, -6, 0, -6, 3, 4, 5]  # max 7 held 3 times, min -6 held 3 times
    y[:, 1] = [1, 7, 7, 0, 2, -6, -6, 0, 1, 3, 4, 5]  # max held twice, min twice: no rail
    y[:, 2] = 2.0  # a constant channel has no rail
    r = plateau_rails(y)
    assert r[:, 0].tolist() == [-6, 7]
    assert np.isnan(r[:, 1:]).all()
    m = saturation_mask(y, "auto")
    assert np.flatnonzero(m.masked).tolist() == [1, 2, 3, 5, 6, 8]
    # a rail found on one side only: the data's range (13) stands for the full range; margin 0.1 -> 1.3
    y[:, 0] = [1, 7, 7, 7, 2, -6, -5, 0, 6, 3, 4, 5]
    m = saturation_mask(y, "auto", margin=0.1)
    assert np.flatnonzero(m.masked).tolist() == [1, 2, 3, 8] and not m.low.any()


def test_rails_from_the_readers():
    # MIMU packets are int16 whatever the declared scale: the rails are −32768 and +32767 counts, converted.
    # (count - 10) * -0.5: a negative scale swaps the rails (a problem file cannot declare one, parse_units
    # refuses it; a conversion made in code can)
    conv = UnitConversion("accelerometer", np.full(3, -0.5), np.full(3, 10.0))
    r = declared_rails(type(conv)(conv.quantity, conv.scale, conv.offset, rails=INT16_RAILS), None, ["a"], [])
    np.testing.assert_array_equal(r["accelerometer"]["a"], [[(32767 - 10) * -0.5] * 3, [(-32768 - 10) * -0.5] * 3])
    assert "gyroscope" not in r
    # a counts declaration with rails (an unsigned 16-bit converter), the offset and scale per axis
    conv = parse_units({"unit": "counts", "scale": [2, 4, 8], "offset": 100, "rails": [0, 65535]}, "p.yaml", "u",
                       "gyroscope")
    np.testing.assert_array_equal(conv.rails_si(), [[-200, -400, -800], [130870, 261740, 523480]])
    assert parse_units(conv.to_dict(), "p.yaml", "u", "gyroscope") == conv
    assert parse_units({"unit": "counts", "scale": 1}, "p.yaml", "u", "gyroscope").rails_si() is None
    rec = Recording(np.arange(3.0), {"a": np.zeros((3, 3))}, rails={"accelerometer": {"a": np.eye(2, 3)}})
    assert rec.select(np.array([True, False, True])).rails_of("a", "accelerometer") is not None
    assert rec.rails_of("a", "gyroscope") is None


@pytest.mark.parametrize("mapping, where, message", [
    ({"margin": -0.01}, "data.saturation.margin", "expected a number from 0 to 0.1"),
    ({"margin": 0.5}, "data.saturation.margin", "expected a number from 0 to 0.1"),
    ({"margin": "wide"}, "data.saturation.margin", "expected a finite number, found 'wide'"),
    ({"adjacent": 1.5}, "data.saturation.adjacent", "expected an integer, found 1.5"),
    ({"adjacent": -1}, "data.saturation.adjacent", "expected an integer from 0 to 10"),
    ({"gyroscope": -3}, "data.saturation.gyroscope", "expected a positive finite number"),
    ({"gyroscope": "sometimes"}, "data.saturation.gyroscope", "expected auto, none or a level in rad/s"),
    ({"rails": [0, 1]}, "data.saturation.rails", "unknown key"),
    ("auto", "data.saturation", "expected a mapping"),
])
def test_saturation_option_errors(mapping, where, message):
    with pytest.raises(InputError, match=message) as e:
        SaturationOptions.from_mapping(mapping, "p.yaml")
    assert f"p.yaml: {where}: " in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("rails, quantity, message", [
    ([1], "gyroscope", "expected [lowest, highest] count"),
    ("int16", "gyroscope", "expected [lowest, highest] count"),
    ([0, "max"], "gyroscope", "expected two finite numbers"),
    ([0, float("inf")], "accelerometer", "expected two finite numbers"),
    ([True, 3], "accelerometer", "expected two finite numbers"),
    ([5, 5], "accelerometer", "expected the lowest count below the highest"),
    ([0, 10], "temperature", "not temperature"),
])
def test_rails_declaration_errors(rails, quantity, message):
    with pytest.raises(InputError, match=__import__("re").escape(message)) as e:
        parse_units({"unit": "counts", "scale": 1, "rails": rails}, "p.yaml", "data.units.x", quantity)
    assert "p.yaml: data.units.x.rails: " in str(e.value)


def test_csv_counts_declared_with_rails_carry_them(tmp_path):
    from castimate.io.readers import read_csv

    p = tmp_path / "d.csv"
    p.write_text("t,a.ax,a.ay,a.az,a.gx,a.gy,a.gz\n0,1,2,3,4,5,6\n0.01,1,2,3,4,5,6\n")
    rec = read_csv(p, {"unit": "counts", "scale": 2.0, "offset": 1, "rails": [-8, 7]},
                   {"unit": "counts", "scale": 1.0, "scale_unit": "deg/s"})
    np.testing.assert_array_equal(rec.rails_of("a", "accelerometer"), [[-18.0] * 3, [12.0] * 3])
    assert rec.rails_of("a", "gyroscope") is None  # not declared: found as plateaus, if any

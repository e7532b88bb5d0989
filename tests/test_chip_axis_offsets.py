"""The chip model's sensing-element offsets shared by every triad of a board
(``accelerometer.chip_axis_offsets``, issue 11): the hand-computed term on both mountings of the
MIMU4444, the gauge the mountings leave, derivatives against finite differences, recovery from a
session the simulator makes independently, problem-file validation and the diagnose candidate order."""

import casadi as ca
import numpy as np
import pytest

from castimate.models import effects as fx
from castimate.problem.effects import BY_KEY, group_names
from castimate.simulate.dynamic import CARLSSON_BOTTOM_ROTATION
from castimate.simulate.effects import CHIP_AXIS_OFFSETS

from test_effects import assert_dynamic_jacobian_matches_finite_differences, dynamic_effect_case

BOTTOM = np.asarray(CARLSSON_BOTTOM_ROTATION, float)  # [[0,-1,0],[-1,0,0],[0,0,-1]], body -> chip


def ev(expr):
    return np.asarray(ca.DM(ca.evalf(expr))).ravel()


def term(R, d, omega, omega_dot):
    R = ca.DM(R)
    return ev(fx.chip_axis_offsets(R, R, ca.DM(d), ca.DM(omega), ca.DM(omega_dot)))


def test_chip_axis_offsets_by_hand_on_both_sides_of_the_board():
    # d_y = (0, 1 mm, 0) in the chip frame: the y element 1 mm along its own axis. Spun at 10 rad/s
    # about the board normal, it reads the centripetal -ω² · 1 mm = -0.1 m/s^2 on either side
    # (top: δ_y = (0, 1 mm, 0); bottom: δ_y = R̄ᵀ d_y = (-1 mm, 0, 0), read along -x)
    for R in (np.eye(3), BOTTOM):
        assert np.allclose(term(R, [0, 1e-3, 0, 0, 0, 0], [0, 0, 10.0], [0, 0, 0]), [0, -0.1, 0])
    # d_z = (0, 1 mm, 0), ω̇ = 100 rad/s^2 about body y: on the top side δ_z ∥ ω̇, nothing; on the
    # bottom δ_z = (-1 mm, 0, 0), ω̇ × δ_z = (0, 0, 0.1), read along the chip's z = body -z: -0.1
    assert np.allclose(term(np.eye(3), [0, 0, 0, 0, 1e-3, 0], [0, 0, 0], [0, 100.0, 0]), [0, 0, 0])
    assert np.allclose(term(BOTTOM, [0, 0, 0, 0, 1e-3, 0], [0, 0, 0], [0, 100.0, 0]), [0, 0, -0.1])


def test_chip_to_body_numbers_and_symbols_agree():
    d = np.array([1.0, 2.0, 3.0, -4.0, 5.0, 0.5]) * 1e-4
    assert np.allclose(fx.chip_to_body(BOTTOM, d), [-2e-4, -1e-4, -3e-4, -5e-4, 4e-4, -0.5e-4])
    assert np.allclose(ev(fx.chip_to_body(ca.DM(BOTTOM), ca.DM(d))), fx.chip_to_body(BOTTOM, d))


def test_gauge_of_the_mountings():
    # one mounting: every chip-frame offset is absorbed by the specific force s and the positions
    assert fx.chip_offsets_gauge([np.eye(3)] * 4).shape == (6, 6)
    # both sides of the board, positions free: Δd_z arbitrary with Δd_y = (I - R̄) Δd_z (all z-sensing
    # elements moved together, the bottom chips with them)
    g = fx.chip_offsets_gauge([np.eye(3), BOTTOM, np.eye(3), BOTTOM])
    assert g.shape == (3, 6)
    expected = np.hstack([(np.eye(3) - BOTTOM).T, np.eye(3)])  # rows (Δd_y, Δd_z) for Δd_z = e_x, e_y, e_z
    assert np.linalg.matrix_rank(np.vstack([g, expected]), 1e-9) == 3
    # positions fixed: only d_z along (1, -1, 0), which R̄ maps onto itself, is left to s
    g = fx.chip_offsets_gauge([np.eye(3), BOTTOM, np.eye(3)], np.zeros((3, 3), bool))
    assert g.shape == (1, 6)
    assert np.allclose(np.abs(g[0]), [0, 0, 0, 2 ** -0.5, 2 ** -0.5, 0]) and g[0, 3] * g[0, 4] < 0


def chip_case(n=600, seed=4):
    rng = np.random.default_rng(11)
    d = np.array([0.3, -0.2, 0.1, -0.25, 0.4, 0.15]) * 1e-3 + 1e-4 * rng.standard_normal(6)
    return dynamic_effect_case(n=n, seed=seed, effects={CHIP_AXIS_OFFSETS: d}), d


def test_chip_axis_offsets_jacobian_matches_finite_differences():
    (cfg, data, _), _ = chip_case(n=30)
    assert_dynamic_jacobian_matches_finite_differences(cfg, data, "chip_axis_offsets")


def test_chip_axis_offsets_recovered_within_sigma():
    """Offsets of 0.1-0.4 mm simulated exactly (each element at its own point, through the simulator's
    own mounting rotations) on 8 IMUs of both sides: recovered within the reported σ's, the gauge
    component zx fixed (zy then estimates d_zx + d_zy), one group for the board, positions unbiased."""
    from castimate.problem.dynamic import build_dynamic
    from castimate.solver.ipopt import Solver

    (cfg, data, _), d = chip_case()
    prob = build_dynamic(cfg, data)
    names = [g.name for g in prob.lsq.layout.groups if "axis_offsets" in g.name]
    assert names == group_names(BY_KEY["accelerometer.chip_axis_offsets"], cfg.names) == [
        "array.accelerometer.chip_axis_offsets"]
    g = prob.lsq.layout.groups[[x.name for x in prob.lsq.layout.groups].index(names[0])]
    assert g.free.ravel().tolist() == [True] * 3 + [False] * 3  # the gauge: d_z taken at the x element
    sol = Solver(prob.lsq).solve()
    assert sol.success, sol.message
    est, std = sol.values[names[0]], sol.std[names[0]]
    assert np.all(est[3:] == 0) and np.all(std[3:] == 0)
    # what the data determine: d_y - (I - R̄_bottom) d_z; the bottom chips' x elements move with the gauge
    shift = -(np.eye(3) - BOTTOM) @ d[3:]
    z = (est[:3] - (d[:3] + shift)) / std[:3]
    assert np.abs(z).max() < 4.5, z
    assert std[:3].max() < 0.1 * np.abs(d[:3] + shift).max(), std
    assert abs(sol.chi2 - sol.dof) < 5 * np.sqrt(2 * sol.dof)
    assert not Solver(prob.lsq).undetermined(sol.x)


def test_without_the_chip_offsets_the_fit_is_worse():
    # the same session fitted without the effect: χ² grows by far more than its 5 parameters
    from dataclasses import replace

    from castimate.problem.dynamic import build_dynamic
    from castimate.solver.ipopt import Solver

    (cfg, data, _), _ = chip_case()
    cfg0 = replace(cfg, effects=())
    s1 = Solver(build_dynamic(cfg, data).lsq).solve()
    s0 = Solver(build_dynamic(cfg0, data).lsq).solve()
    assert s0.success and s1.success
    assert s0.chi2 - s1.chi2 > 100


# --------------------------------------------------------------------------- problem files

ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]


def _problem(tmp_path, model_edits: dict, names=None):
    """problems/mimu4444_exp1_dynamic.yaml with absolute paths and ``model_edits`` merged into ``model``."""
    import yaml

    src = ROOT / "problems" / "mimu4444_exp1_dynamic.yaml"
    doc = yaml.safe_load(src.read_text())
    doc["data"]["path"] = str((src.parent / doc["data"]["path"]).resolve())
    doc["model"]["intrinsics"] = str((src.parent / doc["model"]["intrinsics"]).resolve())
    for k, v in model_edits.items():
        doc["model"][k] = {**(doc["model"].get(k) or {}), **v}
    if names:
        for t, n in zip(doc["array"]["triads"], names):
            t["name"] = n
        doc["model"]["triads"] = {names[0]: doc["model"]["triads"]["imu1"]}
        doc["array"]["reference"] = names[0]
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False))
    return p


needs_data = pytest.mark.skipif(not (ROOT / "problems" / "mimu4444_exp1_dynamic.yaml").exists()
                                or not (ROOT.parent / "shared" / "data" / "mimu4444" / "exp_1").exists(),
                                reason="the MIMU4444 recording is not here")


@needs_data
def test_chip_axis_offsets_is_one_setting_for_the_array(tmp_path):
    from castimate.spec import load_problem

    spec = load_problem(_problem(tmp_path, {"accelerometer": {"chip_axis_offsets": "free"}}))
    assert "accelerometer.chip_axis_offsets" in spec.model.effects
    assert {spec.model.settings[n, "accelerometer", "chip_axis_offsets"].free for n in spec.array.names} == {(True,) * 6}


@needs_data
@pytest.mark.parametrize("edits, names, where, found", [
    ({"triads": {"imu3": {"accelerometer": {"chip_axis_offsets": "free"}}}}, None,
     "model.triads.imu3.accelerometer.chip_axis_offsets", "is one group for the whole array"),
    ({"accelerometer": {"chip_axis_offsets": "free", "axis_offsets": "free"}}, None,
     "model.accelerometer.chip_axis_offsets", "include one of the two, not both"),
    ({"accelerometer": {"chip_axis_offsets": "free"}}, ["array"] + [f"imu{i}" for i in range(2, 9)],
     "model.accelerometer.chip_axis_offsets", "a triad called 'array' would clash with"),
], ids=["per_triad", "both", "triad_named_array"])
def test_chip_axis_offsets_problem_file_errors(tmp_path, edits, names, where, found):
    from test_validation import expect_error

    from castimate.spec import load_problem

    p = _problem(tmp_path, edits, names)
    expect_error(lambda: load_problem(p), p, where, found)


# --------------------------------------------------------------------------- diagnose

def test_diagnose_tries_the_shared_offsets_before_the_per_triad_ones():
    """The per-triad offsets wait until the shared ones were passed over; neither once the other is in."""
    from types import SimpleNamespace

    from castimate.kinds.diagnose import candidates

    session = SimpleNamespace(spec=SimpleNamespace(kind="dynamic_array"), has_temperature=lambda: False)
    model = lambda *eff: SimpleNamespace(effects=eff, outcome=SimpleNamespace(  # noqa: E731
        problem=SimpleNamespace(gyro_triads=["imu1"])))
    keys = lambda m, tried=(): {e.key for e in candidates(session, m, tried)}  # noqa: E731
    shared, per = "accelerometer.chip_axis_offsets", "accelerometer.axis_offsets"
    assert shared in keys(model()) and per not in keys(model())
    assert per in keys(model(), {shared})
    assert not {shared, per} & keys(model(shared), {shared})
    assert not {shared, per} & keys(model(per))

"""One pipeline for every kind: the registry, the protocol, and the outputs table."""

import inspect

import numpy as np
import pytest

from castimate.errors import InputError
from castimate.kinds import REGISTRY, Kind, kind_of
from castimate.output import OUTPUTS
from castimate.simulate.scenarios import simulate_scenario
from castimate.spec import load_problem

SCENARIO = """
seed: 3
kind: static_array
triads: 3
poses: 12
"""


def protocol_members():
    return {n for n, v in vars(Kind).items() if not n.startswith("_") and callable(v)} | {"name", "sampled"}


def test_every_registered_kind_implements_the_protocol_and_has_outputs():
    for name in REGISTRY:
        kind = kind_of(name)
        assert kind.name == name and name in OUTPUTS
        for member in protocol_members():
            assert hasattr(kind, member), f"{name} lacks {member}"
        for member in protocol_members() - {"name", "sampled"}:
            want = list(inspect.signature(getattr(Kind, member)).parameters)[1:]
            assert list(inspect.signature(getattr(kind, member)).parameters) == want, f"{name}.{member}"
    assert set(OUTPUTS) == set(REGISTRY)


def test_an_unknown_kind_is_refused():
    with pytest.raises(InputError, match=r"kind: expected one of static_array, dynamic_array, ferraris, found 'nope'"):
        kind_of("nope")


@pytest.fixture(scope="module")
def static_problem(tmp_path_factory):
    d = tmp_path_factory.mktemp("kinds")
    (d / "s.yaml").write_text(SCENARIO)
    return load_problem(simulate_scenario(d / "s.yaml", d)["problem"])


def test_the_steps_compose_to_the_kinds_calibration(static_problem):
    """load -> configure -> build -> check -> solve gives the optimum of kind.calibrate."""
    from castimate.solver.ipopt import Solver

    kind = kind_of(static_problem)
    data = kind.load(static_problem)
    config = kind.configure(static_problem, data)
    problem = kind.build(config, data)
    solver = Solver(problem.lsq, static_problem.solver)
    kind.check(static_problem, problem, solver, data)
    sol = solver.solve()
    out = kind.calibrate(static_problem, data, quick=True)
    assert out.consistency is None and sol.success
    np.testing.assert_allclose(sol.x, out.solution.x, rtol=1e-10, atol=1e-12)
    t, res = kind.residuals(out)
    assert t.shape == (data.averages.n_poses,) and set(res["accelerometer"]) == set(config.names)


def test_a_static_window_takes_consecutive_poses(static_problem):
    kind = kind_of(static_problem)
    data = kind.load(static_problem)
    part, note = kind.window(static_problem, data, 2, 5)
    assert part.averages.n_poses == 5 and note == "poses 2..6 of 12"
    np.testing.assert_array_equal(part.averages.t_start, data.averages.t_start[2:7])
    with pytest.raises(InputError, match=r"data: expected 1\.\.2 poses from pose 10 \(the problem has 12\), found 3"):
        kind.window(static_problem, data, 10, 3)


def test_fitted_estimates_outside_their_physical_range_are_refused(tmp_path):
    """A converged fit with a gain, an effect or a dynamic problem's position outside its physical range
    (GroupDef.physical_range) is refused in one line naming the data file and the triad's column."""
    from types import SimpleNamespace

    from castimate.kinds.static import check_estimates

    spec = SimpleNamespace(data=SimpleNamespace(path=tmp_path / "data.csv"))
    fine = {"imu1.accelerometer.gain": np.ones(3), "imu1.position": np.array([0.01, 0.02, 0.0]),
            "imu1.gyroscope.coupling": np.zeros(3), "omega": np.full((5, 3), 1e9)}  # motion is not a parameter group
    check_estimates(spec, fine, ["imu1"])
    for key, value, column, found in (("imu1.gyroscope.gain", [1.0, -7.5e8, 1.0], "imu1.gy", "-7.5e+08"),
                                      ("imu1.position", [0.0, 0.0, 12.0], "imu1", "12"),
                                      ("imu1.gyroscope.coupling", [0.0, 2.0, 0.0], "imu1", "2")):
        with pytest.raises(InputError) as err:
            check_estimates(spec, {**fine, key: np.array(value)}, ["imu1"])
        text = str(err.value)
        assert "data.csv" in text and column in text and f"at {found}, outside its physical range" in text, text
        assert "\n" not in text

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

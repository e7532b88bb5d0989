"""FactorBlock.shared_data: the part of a sensor factor that depends on the calibration inputs and
the triad's R̄ alone (T = K L M R̄) is computed once per call of the stage functions instead of once
per sample; the assembly is the same bit for bit, and a data vector whose declared-shared columns
differ between the samples of a triad is refused."""

import dataclasses

import numpy as np
import pytest
from test_assembly import dynamic_case
from test_threads import _arrays

from castimate.problem.dynamic import R_COLUMNS
from castimate.problem.graph import LeastSquaresProblem, SolverOptions
from castimate.solver import elimination
from castimate.solver.ipopt import Solver


def _without_shared(prob):
    blocks = [dataclasses.replace(b, shared_data=()) for b in prob.lsq.blocks]
    return LeastSquaresProblem(prob.lsq.layout, blocks)


@pytest.mark.parametrize("process_model", [True, False])
def test_shared_part_once_per_call_gives_the_same_assembly(monkeypatch, process_model):
    monkeypatch.setattr(elimination, "STAGE_CHUNK", 40)  # several calls per block
    prob = dynamic_case(60, process_model)
    assert all(b.shared_data == R_COLUMNS for b in prob.lsq.blocks if b.name.endswith("_sample"))
    P = Solver(prob.lsq, SolverOptions()).projection
    Q = Solver(_without_shared(prob), SolverOptions()).projection
    assert any("full_shared" in u.stage_fns.fns for u in P.units if u.stage_fns is not None)
    assert not any("full_shared" in u.stage_fns.fns for u in Q.units if u.stage_fns is not None)
    lay = prob.lsq.layout
    x = lay.x0() * (1 + 0.01 * np.random.default_rng(2).standard_normal(lay.n_x))
    pf = lay.p0()
    th, Xs = P.split(x)
    for mode in ("full", "grad", "info", "inner"):
        a, b = P.assemble(th, Xs, pf, None, mode), Q.assemble(th, Xs, pf, None, mode)
        assert a.f == b.f
        for ea, eb in zip(_arrays(a), _arrays(b), strict=True):
            np.testing.assert_array_equal(ea, eb)
    np.testing.assert_array_equal(P.residuals(x, pf, None), Q.residuals(x, pf, None))


def test_same_solve_with_and_without_the_shared_part():
    prob = dynamic_case(60, False)
    a = Solver(prob.lsq, SolverOptions()).solve()
    b = Solver(_without_shared(prob), SolverOptions()).solve()
    assert a.success and b.success and a.iterations == b.iterations
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.covariance, b.covariance)


@pytest.mark.parametrize("instance", [9, -1])
def test_data_whose_shared_columns_differ_use_the_functions_without_the_shared_part(monkeypatch, instance):
    """Data in which a triad's R̄ differs between samples (any data vector is allowed): the calls
    fall back to the local functions without the shared part, with the same assembly as a
    projection that never had one; data with R̄ shared again use the shared part again."""
    monkeypatch.setattr(elimination, "CHECK_STAGES", 7)  # checked slab by slab: the last one too
    prob = dynamic_case(60, False)
    solver = Solver(prob.lsq, SolverOptions())
    P, Q = solver.projection, Solver(_without_shared(prob), SolverOptions()).projection
    blk = next(b for b in solver.blocks if b.block.name == "accelerometer_sample")
    sf = next(u.stage_fns for u in P.units if u.b.block.name == "accelerometer_sample")
    data = prob.lsq.pack([b.data for b in prob.lsq.blocks])
    lay = prob.lsq.layout
    th, Xs = P.split(lay.x0() * 1.001)
    bad = data.copy()
    instance %= blk.block.n
    bad[blk.data_offset + instance * blk.f.nd + R_COLUMNS[4]] += 1e-3  # one sample's R̄ of one triad
    for d in (data, bad, data):
        a, b = P.assemble(th, Xs, lay.p0(), d, "full"), Q.assemble(th, Xs, lay.p0(), d, "full")
        assert a.f == b.f
        for ea, eb in zip(_arrays(a), _arrays(b), strict=True):
            np.testing.assert_array_equal(ea, eb)
        pk = sf.shared_values("full", np.take(np.r_[lay.x0(), lay.p0()], blk.w_idx[:sf.K, :sf.nc]),
                              d[blk.data_offset: blk.data_offset + blk.block.n * blk.f.nd].reshape(blk.block.n, -1),
                              blk.block.n // sf.K)
        assert (pk is None) == (d is bad)
    assert sf._plain_fns is not None

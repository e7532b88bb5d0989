"""Projection.residuals writes every block's residuals into one array (the stage functions' output
in place): the same values as the blocks' own arrays, concatenated."""

import numpy as np
import pytest

from castimate.problem.graph import SolverOptions
from castimate.solver import elimination
from castimate.solver.ipopt import Solver
from test_assembly import dynamic_case


@pytest.mark.parametrize("process_model", [True, False])
def test_residuals_in_one_array_equal_the_blocks(monkeypatch, process_model):
    monkeypatch.setattr(elimination, "STAGE_CHUNK", 64)  # several calls per block
    prob = dynamic_case(80, process_model)
    solver = Solver(prob.lsq, SolverOptions())
    P = solver.projection
    assert any(u.stage_fns is not None for u in P.units)
    rng = np.random.default_rng(4)
    x = prob.lsq.layout.x0() * (1 + 0.01 * rng.standard_normal(prob.lsq.layout.n_x))
    pf = prob.lsq.layout.p0()
    blocks = P.local(x, pf, None, "res")
    pi, pm, ps = P.prior
    expected = np.concatenate([a.ravel() for a in blocks] + [(x[pi] * P.xscale[pi] - pm) / ps])
    np.testing.assert_array_equal(P.residuals(x, pf, None), expected)
    # and the stage function refuses an output it cannot write
    sf = next(u.stage_fns for u in P.units if u.stage_fns is not None)
    u = next(u for u in P.units if u.stage_fns is sf)
    sb, W, nc = u.st[1], u.b.w_idx, u.b.f.n_cal
    w = np.concatenate([x * P.xscale, pf])
    args = (np.take(w, W[: sb.K, :nc]), np.take(w, W[0: 2 * sb.K: sb.K, nc:]), u.b.data[: 2 * sb.K].reshape(2, -1))
    _, (T,) = sf("vec", *args)
    with pytest.raises(ValueError, match="output 0 must be a C-contiguous"):
        sf("vec", *args, into={0: np.empty((2, T.shape[1] + 1))})
    with pytest.raises(ValueError, match="output 0 must be a C-contiguous"):
        sf("vec", *args, into={0: np.empty((T.shape[1], 2)).T})
    out = np.empty_like(T)
    _, (written,) = sf("vec", *args, into={0: out})
    assert written is out
    np.testing.assert_array_equal(out, T)

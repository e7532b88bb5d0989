"""The stage functions' results added onto the eliminated system (elimination._StageFunctions.add):
scattered targets added by flat indices into their slab give the same assembly bit for bit as
numpy's (rows, columns) fancy indexing."""

import numpy as np
import pytest

from castimate.problem.graph import SolverOptions
from castimate.solver import elimination
from castimate.solver.ipopt import Solver
from test_assembly import dynamic_case
from test_threads import _arrays, _point


@pytest.mark.parametrize("process_model", [True, False])
def test_flat_adds_equal_the_fancy_indexed_ones(monkeypatch, process_model):
    """Every mode's assembly with scattered targets added by flat indices equals the one with
    numpy's fancy indexing (flat_add False), bit for bit, on 1 and 2 threads; the case has
    scattered targets (the gyroscopes' share of the coupling)."""
    monkeypatch.setattr(elimination, "STAGE_CHUNK", 24)  # several calls per block
    prob = dynamic_case(90, process_model)
    x, pf = _point(prob)
    P = Solver(prob.lsq, SolverOptions(threads=2)).projection
    assert any(dest is not None for sf in P.stage_fns for lay in sf.layout.values() for *_, dest in lay[2])
    th, Xs = P.split(x)
    for mode in ("full", "grad", "info", "inner", "res"):
        for threads in (2, 1):
            P.threads = threads
            monkeypatch.setattr(elimination._StageFunctions, "flat_add", True)  # noqa: SLF001
            a = P.assemble(th, Xs, pf, None, mode, reuse=True)
            monkeypatch.setattr(elimination._StageFunctions, "flat_add", False)  # noqa: SLF001
            b = P.assemble(th, Xs, pf, None, mode)
            assert a.f == b.f
            for ea, eb in zip(_arrays(a), _arrays(b), strict=True):
                np.testing.assert_array_equal(ea, eb)

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
    _same_with_and_without(monkeypatch, "flat_add", P, x, pf)


def _same_with_and_without(monkeypatch, switch, P, x, pf):
    """Every mode's assembly at x with _StageFunctions' ``switch`` on (into reused arrays filled
    with NaN first) equals the one with it off (fresh arrays), bit for bit, on 2 and 1 threads."""
    th, Xs = P.split(x)
    for mode in ("full", "grad", "info", "inner"):
        for threads in (2, 1):
            P.threads = threads
            monkeypatch.setattr(elimination._StageFunctions, switch, True)  # noqa: SLF001
            P.assemble(th, Xs, pf, None, mode, reuse=True)
            for a in _arrays(P._reused["coupled" if mode in ("full", "info") else mode]):  # noqa: SLF001
                a.fill(np.nan)
            a = P.assemble(th, Xs, pf, None, mode, reuse=True)
            monkeypatch.setattr(elimination._StageFunctions, switch, False)  # noqa: SLF001
            b = P.assemble(th, Xs, pf, None, mode)
            assert a.f == b.f
            for ea, eb in zip(_arrays(a), _arrays(b), strict=True):
                np.testing.assert_array_equal(ea, eb)


@pytest.mark.parametrize("process_model, reverse", [(True, False), (False, False), (True, True)])
def test_direct_writes_equal_the_added_ones(monkeypatch, process_model, reverse):
    """Dense targets that the stage functions write straight into the assembled arrays (direct)
    give every mode's assembly bit for bit as when they are added onto zeroed arrays, on 1 and 2
    threads; the reused arrays are filled with NaN first, so a row that no direct write covers, or
    an array that zero() left but nothing wrote whole, shows. ``reverse``: the blocks in reverse
    order, so that the process model comes first: its stage gradient lands on G from two stage
    offsets, and its J - 1 stage groups do not cover the last row; neither may be written in place."""
    monkeypatch.setattr(elimination, "STAGE_CHUNK", 24)  # several calls per block, several in flight
    prob = dynamic_case(90, process_model)
    x, pf = _point(prob)
    P = Solver(prob.lsq, SolverOptions(threads=2)).projection
    if reverse:
        P.units.reverse()
        P._written = {mode: P._direct(mode) for mode in P._written}  # noqa: SLF001
        first = P.units[0]
        assert first.b.block.name == "process_model" and first.st[1].J == 89
        assert not first.direct["full"] and not first.direct["grad"]
        assert not any(P._written.values())  # noqa: SLF001 (every later block finds its arrays written)
    else:  # the accelerometers come first and write G, B[0] and the coupling whole
        assert P._written["full"] == {("G", 0, None), ("B", 0, 0), ("Hsc", 0, None)}  # noqa: SLF001
        assert P._written["info"] == {("B", 0, 0), ("Hsc", 0, None)}  # noqa: SLF001
    _same_with_and_without(monkeypatch, "direct", P, x, pf)


def test_which_dense_targets_are_written_in_place():
    """Projection._direct by hand: a dense segment is written in place only if its array is not
    written before (by an earlier block, or by any block without stage functions), no other
    segment of its block lands on it, and its stage groups cover every row of it."""
    from types import SimpleNamespace as NS

    def unit(J, base, segs, staged=True):
        layout = {"full": (True, [], [(label, key, o, 0, 1, dest) for o, (label, key, dest) in enumerate(segs)], 1, [])}
        return NS(st=(0, NS(J=J, base=base)), stage_fns=NS(layout=layout) if staged else None, direct={})

    fam = NS(R=10, width=2)
    dense, scattered = None, np.arange(2)
    units = [
        unit(9, 0, [("G", 0, dense)]),  # 9 of 10 rows: added
        unit(10, 0, [("Hsc", 0, dense), ("B", (0, 0), dense), ("Bgn", (1, 0), scattered)]),
        unit(10, 0, [("B", (0, 0), dense), ("Hsc", 0, scattered)]),  # both written before: added
        unit(9, 0, [("B", (0, 1), dense), ("B", (1, 1), scattered)]),  # B[1] from two segments: added
        unit(9, 0, [("Bgn", (0, 1), dense)]),  # Bgn[1] has R - 1 = 9 rows: whole
    ]
    P = NS(units=units, fams=[fam])
    assert elimination.Projection._direct(P, "full") == {("Hsc", 0, None), ("B", 0, 0), ("Bgn", 0, 1)}
    assert [u.direct["full"] for u in units] == [set(), {0, 1}, set(), set(), {0}]
    # stage offset 1 of a block (base + d = 1) does not start at the first row; a block without
    # stage functions before the others writes any array of the family
    units = [unit(10, 1, [("G", 0, dense)]), unit(10, 0, [("Hsc", 0, dense)])]
    assert elimination.Projection._direct(NS(units=units, fams=[fam]), "full") == {("Hsc", 0, None)}
    units = [unit(10, 0, [], staged=False), unit(10, 0, [("Hsc", 0, dense)])]
    assert elimination.Projection._direct(NS(units=units, fams=[fam]), "full") == set()

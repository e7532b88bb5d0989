"""The stage analysis of a factor block (castimate.solver.assembly.StagedBlock and
castimate.solver.elimination._stage) on hand-made index matrices.

StagedBlock takes the stage columns from the first instance and gathers only those; the other
columns must then repeat every K instances and read no stage variable. Each way a block can break
that structure is checked to be refused (NotStaged), whichever instance breaks it.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from castimate.solver.assembly import Block, NotStaged, StagedBlock
from castimate.solver.elimination import _stage

N_CAL, R, M, K = 5, 6, 2, 3  # calibration variables, stages, variables per stage, instances per stage


@pytest.fixture(autouse=True, params=[None, 4])
def slab(request, monkeypatch):
    """The checks in one slab, and a stage group per slab (StagedBlock.SLAB)."""
    if request.param is not None:
        monkeypatch.setattr(StagedBlock, "SLAB", request.param)


def family():
    """x = [5 calibration variables | stage s, position p at 5 + 2 s + p]; w = x then 4 fixed values."""
    n = N_CAL + R * M + 4
    stage_of, within = np.full(n, -1), np.full(n, -1)
    X = N_CAL + np.arange(R * M).reshape(R, M)
    stage_of[X] = np.arange(R)[:, None]
    within[X] = np.arange(M)[None, :]
    return SimpleNamespace(stage_of=stage_of, within=within), X


def staged_w_idx():
    """Instance (j, k): [its own calibration variable k, a shared one, a fixed value, stage j's two variables]."""
    _, X = family()
    rows = [[k, 4, N_CAL + R * M + 1, X[j, 0], X[j, 1]] for j in range(R) for k in range(K)]
    return np.array(rows, np.int32)


def test_a_staged_block():
    st, _ = family()
    sb = StagedBlock(SimpleNamespace(w_idx=staged_w_idx()), st)
    assert (sb.K, sb.J, sb.base, sb.n_cal) == (K, R, 0, 3)
    np.testing.assert_array_equal(sb.is_st, [False, False, False, True, True])
    np.testing.assert_array_equal(sb.rel[:, 3:], 0)
    np.testing.assert_array_equal(sb.q[:, 3:], [[0, 1]] * K)
    np.testing.assert_array_equal(sb.q[:, 0], np.arange(K))


@pytest.mark.parametrize("instance", [1, 4, R * K - 1])
def test_a_calibration_column_reading_a_stage_variable_is_refused(instance):
    """Within the first stage group (instance 1) or after it: either way NotStaged."""
    st, X = family()
    W = staged_w_idx()
    W[instance, 1] = X[instance // K, 0]
    with pytest.raises(NotStaged):
        StagedBlock(SimpleNamespace(w_idx=W), st)


def test_a_calibration_column_reading_one_stage_variable_throughout_is_refused():
    """The same stage variable in every stage group (the columns still repeat every K instances)."""
    st, X = family()
    W = staged_w_idx()
    W[1::K, 1] = X[0, 0]
    with pytest.raises(NotStaged):
        StagedBlock(SimpleNamespace(w_idx=W), st)


def test_a_stage_column_reading_a_calibration_variable_is_refused():
    st, _ = family()
    W = staged_w_idx()
    W[7, 3] = 2
    with pytest.raises(NotStaged):
        StagedBlock(SimpleNamespace(w_idx=W), st)


def test_first_instance_without_stage_variables():
    """The stage columns cannot be read off the first instance: the general analysis refuses it."""
    st, _ = family()
    W = staged_w_idx()
    W[0, 3:] = [0, 1]
    with pytest.raises(NotStaged):
        StagedBlock(SimpleNamespace(w_idx=W), st)


def test_no_stage_variables():
    st, _ = family()
    W = staged_w_idx()[:, :3]
    with pytest.raises(LookupError):
        StagedBlock(SimpleNamespace(w_idx=W), st)
    with pytest.raises(LookupError):
        _stage(SimpleNamespace(w_idx=W), st)


def test_stage_sorts_instances_by_stage():
    """Instances given stage-minor are put in stage order (the order is returned)."""
    st, _ = family()
    W = staged_w_idx()
    perm = np.arange(R * K).reshape(R, K).T.ravel()  # triad-major
    segs, order = _stage(SimpleNamespace(w_idx=W[perm]), st)
    assert len(segs) == 1 and order is not None
    np.testing.assert_array_equal(perm[order], np.arange(R * K))
    assert segs[0][2].K == K and segs[0][2].J == R


def test_stage_cuts_a_block_with_clamped_neighbours_into_runs():
    """A factor reading the previous and next stage, clamped at the ends of the record: three runs
    (first stage, interior, last stage), each staged on its own."""
    st, X = family()
    prev, nxt = np.maximum(np.arange(R) - 1, 0), np.minimum(np.arange(R) + 1, R - 1)
    W = np.array([[k, X[prev[j], 0], X[j, 0], X[nxt[j], 0]] for j in range(R) for k in range(K)], np.int32)
    segs, order = _stage(SimpleNamespace(w_idx=W), st)
    assert order is None
    assert [(t0, t1) for t0, t1, _ in segs] == [(0, K), (K, (R - 1) * K), ((R - 1) * K, R * K)]


def test_reorder_in_place_by_slabs():
    """Block.reorder permutes the index matrix's columns in place, a slab of instances at a time."""
    W = np.random.default_rng(1).integers(0, 1000, (23, 6)).astype(np.int32)
    b = Block.__new__(Block)
    b.w_idx, b.order = W.copy(), np.arange(6)
    buffer = b.w_idx
    order = np.array([3, 0, 5, 1, 4, 2])
    b.reorder(order)
    assert b.w_idx is buffer
    np.testing.assert_array_equal(b.w_idx, W[:, order])
    np.testing.assert_array_equal(b.order, order)
    b.reorder(np.argsort(b.order))
    np.testing.assert_array_equal(b.w_idx, W)

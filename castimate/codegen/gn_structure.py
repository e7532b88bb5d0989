"""The structure of a least-squares problem as the C Gauss-Newton solver sees it.

From a :class:`castimate.solver.Solver` (its factor blocks bound to the layout) this module derives,
in numpy, everything the generic C driver ``c/castimate_gn.c`` needs as constant tables:

- the split of the decision vector x into *global* variables (calibration parameters, positions)
  and *local blocks*: one block per row of the nuisance matrix groups (one static pose's gravity
  direction, Nilsson 2014; one sample's ω, ω̇, s, Carlsson 2017). Every residual must involve at
  most one local block, so that J^T J is block-arrow shaped and the local blocks can be eliminated
  one by one (Schur complement onto the global variables);
- each factor block's index matrix into w = [x * scale; p_fixed], run-length encoded as arithmetic
  progressions (a block over thousands of samples is a handful of runs);
- priors and unit-norm rows (|w_row|^2 = 1, as the Python solve's equality constraints);

and, with CasADi, per factor block the residual function ``(z, d) -> r`` and the residual with its
Jacobian with respect to the components free in some instance, ``(z, d) -> (r, J)``. Both are
built from the block's own symbolic residual: the C solver and IPOPT minimise the same function.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..solver.ipopt import Solver


class UnsupportedProblem(ValueError):
    """The problem has a structure the C solver does not handle; the message says which."""


@dataclass(frozen=True)
class BlockTables:
    """One factor block for the C solver."""

    name: str
    n: int  # instances
    nz: int
    nd: int
    m: int  # residuals per instance
    act: np.ndarray  # columns of z that are free in some instance (Jacobian columns)
    runs: list[np.ndarray]  # per column of z: (n_runs, 3) runs (start, step, count) of its w indices
    data0: int  # offset of the block's data in the data vector
    factor: ca.Function  # the problem's own factor function (z, d) -> r
    res: ca.Function  # (z, d) -> r
    res_jac: ca.Function  # (z, d) -> (r, J[:, act]) dense, column-major


def arithmetic_runs(v: np.ndarray) -> np.ndarray:
    """(n_runs, 3) runs (start, step, count) whose concatenation v[i] = start + k * step is v."""
    v = np.asarray(v, int)
    out, i, n = [], 0, len(v)
    while i < n:
        if i + 1 == n:
            out.append((v[i], 0, 1))
            break
        step = v[i + 1] - v[i]
        j = i + 1
        while j + 1 < n and v[j + 1] - v[j] == step:
            j += 1
        out.append((v[i], step, j - i + 1))
        i = j + 1
    return np.array(out, int).reshape(-1, 3)


def expand_runs(runs: np.ndarray) -> np.ndarray:
    """Inverse of :func:`arithmetic_runs`."""
    return np.concatenate([s + d * np.arange(c) for s, d, c in runs]) if len(runs) else np.zeros(0, int)


def block_functions(fn: ca.Function, active: np.ndarray, name: str) -> tuple[ca.Function, ca.Function]:
    """The residual and the residual with its dense Jacobian w.r.t. the active components of z."""
    z, d = ca.SX.sym("z", fn.size1_in(0)), ca.SX.sym("d", fn.size1_in(1))
    r = fn(z, d)
    za = ca.vertcat(*[z[int(i)] for i in np.flatnonzero(active)])
    J = ca.densify(ca.jacobian(r, za))
    return (ca.Function(f"{name}_r", [z, d], [r], ["z", "d"], ["r"]),
            ca.Function(f"{name}_rj", [z, d], [r, J], ["z", "d"], ["r", "J"]))


@dataclass
class GNStructure:
    """Tables of a problem for the C Gauss-Newton solver (see the module docstring)."""

    n_x: int
    n_p: int
    n_data: int
    x_scale: np.ndarray
    x0: np.ndarray
    p0: np.ndarray
    blocks: list[BlockTables]
    x_global: np.ndarray  # (n_x,) position among the global variables, -1 if local
    x_local: np.ndarray  # (n_x,) local block, -1 if global
    x_lpos: np.ndarray  # (n_x,) position within the local block
    loc_x: np.ndarray  # (n_local, lmax) x index of each local position, -1 padded
    loc_c: np.ndarray  # (n_local,) unit-norm constraints per local block
    n_global_constraints: int
    prior_x: np.ndarray
    prior_mean: np.ndarray
    prior_std: np.ndarray
    unit_w: np.ndarray  # (n_unit, umax) w indices of each unit-norm row, -1 padded
    unit_local: np.ndarray  # local block of each unit row, -1 if global
    unit_pos: np.ndarray  # constraint position within its local block, or among the global ones
    value_w: np.ndarray  # w index of every value, groups in layout order, rows x components
    groups: list[tuple[str, int, int, int, bool]]  # (name, offset into the values, rows, components, matrix)
    fixed: list[tuple[str, int, int]]  # (group, offset into p_fixed, count) of the groups with fixed components

    @property
    def n_global(self) -> int:
        return int((self.x_global >= 0).sum())

    @property
    def n_local(self) -> int:
        return self.loc_x.shape[0]

    @property
    def lmax(self) -> int:
        return self.loc_x.shape[1] if self.n_local else 1

    @property
    def cmax(self) -> int:
        return max(int(self.loc_c.max()) if len(self.loc_c) else 0, 1)


def gn_structure(solver: Solver) -> GNStructure:
    """Derive the tables of the C solver from a built :class:`Solver` (its layout and blocks).

    Raises :class:`UnsupportedProblem` if a residual couples two local blocks (a process model
    between samples) or a free component has finite bounds (the C solver is unconstrained apart
    from the unit-norm rows).
    """
    problem = solver.problem
    lay = problem.layout
    n_x = lay.n_x
    lb, ub = lay.bounds()
    if np.isfinite(lb).any() or np.isfinite(ub).any():
        bad = lay.x_labels[int(np.flatnonzero(np.isfinite(lb) | np.isfinite(ub))[0])]
        raise UnsupportedProblem(f"the C solver handles no bounds, but {bad} has one")

    # local blocks: row r of every nuisance matrix group
    x_local = np.full(n_x, -1)
    x_row_of = {}
    for g in lay.groups:
        if g.nuisance and g.matrix:
            W = lay.w_index(g.name)
            for r in range(g.rows):
                for wi in W[r][W[r] < n_x]:
                    x_row_of[int(wi)] = r
    rows_used = sorted(set(x_row_of.values()))
    row_to_local = {r: k for k, r in enumerate(rows_used)}
    for i, r in x_row_of.items():
        x_local[i] = row_to_local[r]
    n_local = len(rows_used)
    members = [[] for _ in range(n_local)]
    for i in range(n_x):
        if x_local[i] >= 0:
            members[x_local[i]].append(i)
    lmax = max((len(m) for m in members), default=1)
    loc_x = np.full((n_local, lmax), -1)
    x_lpos = np.full(n_x, -1)
    for k, m in enumerate(members):
        loc_x[k, :len(m)] = m
        x_lpos[m] = np.arange(len(m))
    x_global = np.full(n_x, -1)
    glob = np.flatnonzero(x_local < 0)
    x_global[glob] = np.arange(len(glob))

    # factor blocks: index runs, data offsets, generated functions
    blocks, data0 = [], 0
    for k, b in enumerate(solver.blocks):
        fb = b.block
        W = np.empty_like(b.w_idx)
        W[:, b.order] = b.w_idx  # the factor function's input order (the Solver may reorder its columns)
        touched = np.where(W < n_x, x_local[np.minimum(W, n_x - 1)], -1)
        lo = np.where(touched >= 0, touched, np.iinfo(int).max).min(axis=1)
        hi = touched.max(axis=1)
        if ((hi >= 0) & (lo != hi)).any():
            raise UnsupportedProblem(f"factor {fb.name} couples two samples or poses (a process model); the C "
                                     "solver eliminates one sample at a time and needs them independent")
        active = (W < n_x).any(axis=0)
        res, res_jac = block_functions(fb.residual, active, f"cs_b{k}_{fb.name}")
        nz, nd = fb.residual.size1_in(0), fb.residual.size1_in(1)
        blocks.append(BlockTables(fb.name, fb.n, nz, nd, fb.residual.size1_out(0), np.flatnonzero(active),
                                  [arithmetic_runs(W[:, j]) for j in range(nz)], data0, fb.residual, res, res_jac))
        data0 += fb.n * nd

    pi, pm, ps = lay.priors()

    # unit-norm rows: all free components in one local block, or all global
    U = lay.unit_norm_rows()
    unit_local, unit_pos = np.full(len(U), -1), np.zeros(len(U), int)
    loc_c = np.zeros(n_local, int)
    n_gc = 0
    for k, row in enumerate(U):
        free = row[(row >= 0) & (row < n_x)]
        locs = set(x_local[free].tolist())
        if len(locs) != 1:
            raise UnsupportedProblem("a unit-norm row mixes global and local variables")
        (l,) = locs
        unit_local[k] = l
        if l >= 0:
            unit_pos[k] = loc_c[l]
            loc_c[l] += 1
        else:
            unit_pos[k] = n_gc
            n_gc += 1

    value_w, groups, fixed, off = [], [], [], 0
    for g in lay.groups:
        W = lay.w_index(g.name)
        value_w.append(W.ravel())
        groups.append((g.name, off, g.rows, g.size, g.matrix))
        off += W.size
        p = W[W >= n_x] - n_x
        if len(p):
            fixed.append((g.name, int(p.min()), len(p)))
    return GNStructure(
        n_x=n_x, n_p=lay.n_p, n_data=problem.data.size, x_scale=lay.x_scale, x0=lay.x0(), p0=lay.p0(),
        blocks=blocks, x_global=x_global, x_local=x_local, x_lpos=x_lpos, loc_x=loc_x, loc_c=loc_c,
        n_global_constraints=n_gc, prior_x=pi, prior_mean=pm, prior_std=ps,
        unit_w=U if U.size else np.full((0, 1), -1), unit_local=unit_local, unit_pos=unit_pos,
        value_w=np.concatenate(value_w), groups=groups, fixed=fixed)

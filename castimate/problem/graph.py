"""The factor graph every kind composes: parameter-group factor blocks, the least-squares problem,
solver options and the solution object (shared by problem/ and solve/).
"""

from __future__ import annotations

import contextvars
import os
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from .parameters import Layout


@dataclass(frozen=True)
class SolverOptions:
    """IPOPT settings with documented defaults.

    Attributes
    ----------
    max_iter
        Iteration limit; hitting it is a failure to converge.
    tol
        IPOPT's overall tolerance (on the scaled KKT error).
    linear_solver
        ``mumps`` (default, fastest in the wheel) or ``spral``.
    print_level
        IPOPT verbosity, 0-12.
    hessian
        ``exact`` (default): the exact Hessian of the Lagrangian. ``gauss_newton``: J^T J plus the
        constraint curvature, more robust far from the solution.
    identifiability_tol
        Relative eigenvalue of the Fisher information below which a direction counts as not
        determined by the data.
    method
        ``ipopt`` (default) or ``bcd``: Carlsson 2017's block coordinate descent (Algorithm 1), a
        baseline for dynamic problems with gyroscopes where only positions are free.
    jit
        Compile the factors' local functions to C (:mod:`castimate.jit`, cached on disk) where one
        evaluation runs enough instances to repay gcc (:func:`castimate.jit.worth_compiling`); the
        results are the same as on CasADi's virtual machine, about ten times faster.
    elimination
        ``motion`` (default): IPOPT solves for the calibration parameters only, with the per-sample
        motion and the per-pose directions eliminated exactly at every iterate (variable projection,
        :mod:`castimate.solver.elimination`): time and memory per iteration linear in the samples,
        only the calibration parameters dense. ``none``: the full NLP with every nuisance variable,
        its KKT system factorised by MUMPS (the reference path). Problems without such nuisance
        rows solve the same either way.
    covariance
        Compute the Fisher covariance and the σ's at the solution (default). ``False`` leaves
        ``Solution.covariance`` None and ``Solution.std`` empty: for fits whose estimates alone are
        used, e.g. the folds of a cross-validation (not a problem-file key).
    threads
        Worker threads for the compiled local functions of the eliminated problem (``elimination:
        motion``): more than 1 runs chunks of samples in parallel (the compiled code runs without
        Python's lock) with results identical to one thread's. None (default, ``auto`` in a problem
        file): one per core this process may run on, at most 8, and 1 inside the tasks of
        ``castimate batch``, ``montecarlo`` and ``plan``, which already put one solve on each core
        (:func:`castimate.solver.ipopt.solver_threads`).
    """

    method: str = "ipopt"
    max_iter: int = 200
    tol: float = 1e-8
    linear_solver: str = "mumps"
    print_level: int = 0
    hessian: str = "exact"
    identifiability_tol: float = 1e-10
    jit: bool = True
    elimination: str = "motion"
    covariance: bool = True
    threads: int | None = None

    def ipopt(self) -> dict:
        return {
            "ipopt.max_iter": self.max_iter,
            "ipopt.tol": self.tol,
            "ipopt.linear_solver": self.linear_solver,
            "ipopt.print_level": self.print_level,
            "ipopt.sb": "yes",
            "ipopt.mumps_pivot_order": 5,  # METIS ordering
            # no MUMPS scaling: x is scaled already, and on a 32 x 20 000 problem computing the
            # scalings took a quarter of the factorisation time
            "ipopt.mumps_scaling": 0,
            "ipopt.mumps_permuting_scaling": 0,
            "print_time": False,
            "record_time": True,
            "calc_lam_p": False,
        }


#: The default number of worker threads where castimate already runs one solve per core (the tasks of
#: batch, montecarlo and plan: scale.engine.guarded sets it to 1 around each); None elsewhere.
TASK_THREADS: contextvars.ContextVar[int | None] = contextvars.ContextVar("castimate_task_threads", default=None)
MAX_THREADS = 8


def solver_threads(threads: int | None) -> int:
    """SolverOptions.threads resolved: the number given, or for None the cores this process may run
    on (at most MAX_THREADS), or TASK_THREADS inside a task that shares the cores with others."""
    if threads is None:
        task = TASK_THREADS.get()
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        return task if task is not None else max(1, min(MAX_THREADS, cores))
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"solver threads: expected a positive integer, found {threads!r}")
    return threads


@dataclass
class FactorBlock:
    """One kind of residual term repeated over instances: a factor of the factor graph.

    Attributes
    ----------
    name
        For messages.
    residual
        ``(z, d) -> r``: whitened residual of one instance. ``z`` stacks the values of the
        instance's inputs (physical units), ``d`` its data.
    inputs
        ``(group, rows)`` in the order they stack into ``z``. ``group`` is a group name or a tuple
        of names whose rows are stacked (one plain group per triad, say); ``rows`` (N,) picks a row
        per instance, ``None`` feeds the single row to every instance. One block per kind of factor
        keeps CasADi's graph small: one ``map`` node instead of one per triad.
    data
        (N, nd) data of the instances; they enter the NLP as parameters, so one build serves any
        number of data sets.
    valid
        (N,) instances whose residuals count (default all), or (N, m) per residual row. The data of
        the others must make their residuals exactly zero (a masked sample with σ = inf; a masked
        axis with σ = MASKED_SIGMA): they keep a block's instances on a regular grid, which the solver
        exploits, and are left out of the reported residuals and degrees of freedom.
    series
        (N,) the sample of each instance when the block's residuals form time series (serially
        correlated: the HAC covariance of :mod:`castimate.solver.serial` sums their scores per
        sample over its lags); None: independent instances (Fisher information).
    shared_data
        Data columns that are the same for every instance reading the same calibration rows (a
        sensor block's nominal rotation R̄ of each triad): the eliminated problem's compiled
        functions compute what depends on them and the calibration inputs alone once per call
        instead of once per instance (:mod:`castimate.solver.elimination`), and check every data
        vector they are given for it.
    """

    name: str
    residual: ca.Function
    inputs: list[tuple[str | tuple[str, ...], np.ndarray | None]]
    data: np.ndarray
    valid: np.ndarray | None = None
    series: np.ndarray | None = None
    shared_data: tuple[int, ...] = ()

    @property
    def n(self) -> int:
        return self.data.shape[0]


@dataclass
class LeastSquaresProblem:
    """A whitened least-squares problem: parameter groups plus factor blocks."""

    layout: Layout
    blocks: list[FactorBlock]

    @property
    def data(self) -> np.ndarray:
        return np.concatenate([b.data.ravel() for b in self.blocks])

    def pack(self, block_data: list[np.ndarray]) -> np.ndarray:
        """Data vector from per-block (N, nd) arrays."""
        return np.concatenate([np.asarray(d, float).ravel() for d in block_data])


@dataclass
class Solution:
    """The outcome of one solve, in physical units."""

    success: bool
    message: str
    iterations: int
    wall_s: float
    x: np.ndarray
    values: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    cost: float
    chi2: float
    dof: int
    residual: np.ndarray
    covariance: np.ndarray = field(repr=False)  # of the free calibration components (Solver.theta), physical units
    lam_g: np.ndarray = field(default=None, repr=False)  # constraint multipliers, to warm-start another solve  # of the free calibration components (Solver.theta), physical units
    evaluated: bool = True  # False: IPOPT stopped where the eliminated nuisance has no solution; x is the start
    settled: bool = False  # stopped unconverged by Solver.solve's ``settle`` (an outer iteration's intermediate fit)

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")

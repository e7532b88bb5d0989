"""The one solve path shared by every kind.

A problem is a weighted nonlinear least-squares problem with equality constraints::

    minimise   1/2 |r(x, p)|^2      r: whitened residuals (data and priors)
    subject to c(x, p) = 0          unit-norm constraints
               lbx <= x <= ubx

It is solved by IPOPT with the exact sparse Hessian of the Lagrangian computed by CasADi.
Uncertainty comes from the Fisher information J^T J at the solution, restricted to the tangent
space of the constraints; taking a block of its inverse marginalises the nuisance variables.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from .problem.parameters import Layout


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
    identifiability_tol
        Relative eigenvalue of the Fisher information below which a direction counts as not
        determined by the data.
    """

    max_iter: int = 200
    tol: float = 1e-10
    linear_solver: str = "mumps"
    print_level: int = 0
    identifiability_tol: float = 1e-10

    def ipopt(self) -> dict:
        return {
            "ipopt.max_iter": self.max_iter,
            "ipopt.tol": self.tol,
            "ipopt.linear_solver": self.linear_solver,
            "ipopt.print_level": self.print_level,
            "ipopt.sb": "yes",
            "ipopt.mumps_pivot_order": 5,
            "print_time": False,
            "record_time": True,
        }


@dataclass
class LeastSquaresProblem:
    """A whitened least-squares problem composed from model functions.

    Attributes
    ----------
    layout
        Parameter groups (free -> x, fixed -> p_fixed).
    residual
        Whitened data residuals, an expression of ``layout.x``, ``layout.p`` and ``data_sym``.
    data_sym, data
        Symbols and values of the data (measurements and their σ's). Data enter the NLP as
        parameters, so one build serves any number of data sets.
    """

    layout: Layout
    residual: ca.SX
    data_sym: ca.SX
    data: np.ndarray

    @property
    def all_residuals(self):
        return ca.vertcat(self.residual, self.layout.prior_residuals())


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
    covariance_x: np.ndarray = field(repr=False)

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")


class Solver:
    """IPOPT on a :class:`LeastSquaresProblem`, built once and solved for any data or fixed values."""

    def __init__(self, problem: LeastSquaresProblem, options: SolverOptions = SolverOptions()):
        self.problem, self.options = problem, options
        lay = problem.layout
        r = problem.all_residuals
        c = lay.constraints()
        p = self._p_sym = ca.vertcat(lay.p, problem.data_sym)
        t0 = time.perf_counter()
        nlp = {"x": lay.x, "p": p, "f": 0.5 * ca.sumsqr(r), "g": c}
        self.nlp = ca.nlpsol("castimate", "ipopt", nlp, options.ipopt())
        # Jacobians for the Fisher information and the constraint tangent space.
        self._jac = ca.Function("fisher_jacobians", [lay.x, p], [ca.jacobian(r, lay.x), ca.jacobian(c, lay.x)])
        self._res = ca.Function("data_residual", [lay.x, p], [problem.residual])
        self.n_constraints = c.shape[0]
        self.n_residuals = r.shape[0]
        self.build_s = time.perf_counter() - t0

    def _p(self, p_fixed, data):
        lay = self.problem.layout
        p_fixed = lay.p0() if p_fixed is None else p_fixed
        data = self.problem.data if data is None else data
        return np.concatenate([np.asarray(p_fixed, float), np.asarray(data, float).ravel()])

    def jacobians(self, x, p_fixed=None, data=None) -> tuple[np.ndarray, np.ndarray]:
        """Dense Jacobians (scaled x) of the whitened residuals J and of the constraints G."""
        J, G = self._jac(x, self._p(p_fixed, data))
        return J.full(), G.full()

    def _tangent_fisher(self, x, p_fixed, data) -> tuple[np.ndarray, np.ndarray]:
        """Fisher information J^T J restricted to the constraint tangent space, and its basis U."""
        J, G = self.jacobians(x, p_fixed, data)
        if G.shape[0]:
            Q = np.linalg.qr(G.T, mode="complete")[0]
            U = Q[:, G.shape[0]:]
            JU = J @ U
            return JU.T @ JU, U
        return J.T @ J, np.eye(J.shape[1])

    def undetermined(self, x, p_fixed=None, data=None, top: int = 4) -> list[str]:
        """Directions the data cannot determine at x, each named by its largest components."""
        Fu, U = self._tangent_fisher(x, p_fixed, data)
        w, V = np.linalg.eigh(Fu)
        tol = self.options.identifiability_tol * max(w.max(), 1e-300)
        out = []
        labels = self.problem.layout.x_labels
        for k in np.flatnonzero(w <= tol):
            d = U @ V[:, k]
            idx = np.argsort(-np.abs(d))[:top]
            idx = [i for i in idx if abs(d[i]) > 0.2 * abs(d[idx[0]])]
            out.append(" + ".join(f"{d[i]:+.2f}*{labels[i]}" for i in idx))
        return out

    def covariance(self, x, p_fixed=None, data=None) -> np.ndarray:
        """Covariance of all free components (physical units): the constrained inverse Fisher information.

        Its blocks for calibration parameters are the marginals with the nuisance variables
        integrated out. Computed as the top-left block of the inverse of the KKT matrix
        [[J^T J, G^T], [G, 0]], which equals U (U^T J^T J U)^-1 U^T for a tangent basis U.
        """
        J, G = self.jacobians(x, p_fixed, data)
        n, c = J.shape[1], G.shape[0]
        K = np.zeros((n + c, n + c))
        K[:n, :n] = J.T @ J
        K[n:, :n], K[:n, n:] = G, G.T
        rhs = np.zeros((n + c, n))
        rhs[:n] = np.eye(n)
        try:
            C = np.linalg.solve(K, rhs)[:n]
        except np.linalg.LinAlgError:
            Fu, U = self._tangent_fisher(x, p_fixed, data)  # rank deficient: pseudo-inverse
            C = U @ np.linalg.pinv(Fu, hermitian=True) @ U.T
        s = self.problem.layout.x_scale
        return C * np.outer(s, s)

    def solve(self, x0=None, p_fixed=None, data=None) -> Solution:
        lay = self.problem.layout
        x0 = lay.x0() if x0 is None else np.asarray(x0, float)
        lbx, ubx = lay.bounds()
        p = self._p(p_fixed, data)
        t0 = time.perf_counter()
        sol = self.nlp(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=0, ubg=0)
        wall = time.perf_counter() - t0
        st = self.nlp.stats()
        x = np.asarray(sol["x"]).ravel()
        pf = p[: lay.p.shape[0]]
        values = lay.unpack(x, pf)
        cov = self.covariance(x, pf, p[lay.p.shape[0]:])
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        std = {}
        for g in lay.groups:
            s = np.zeros(g.size)
            s[g.free] = sd[lay.x_indices(g.name)]
            std[g.name] = s
        r = np.asarray(self._res(x, p)).ravel()
        cost = float(sol["f"])
        dof = self.n_residuals - (x.size - self.n_constraints)
        return Solution(
            success=bool(st["success"]),
            message=str(st["return_status"]),
            iterations=int(st["iter_count"]),
            wall_s=wall,
            x=x,
            values=values,
            std=std,
            cost=cost,
            chi2=2.0 * cost,
            dof=int(dof),
            residual=r,
            covariance_x=cov,
        )

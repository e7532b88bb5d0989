"""The one solve path shared by every kind.

A problem is a weighted nonlinear least-squares problem with equality constraints::

    minimise   1/2 |r(x, p)|^2      r: whitened residuals (factor blocks and priors)
    subject to c(x, p) = 0          unit-norm constraints of quaternions and unit vectors
               lbx <= x <= ubx

The residual is a factor graph: each :class:`FactorBlock` is one small CasADi function of a few
parameter groups and a few data, repeated over its instances. Its local residual, Jacobian,
gradient and Hessian are CasADi functions compiled to C (:mod:`castimate.jit`) and evaluated over
chunks of instances in place on numpy arrays (``Function.map`` through a ``FunctionBuffer``).
IPOPT's objective, gradient and exact sparse Hessian of the Lagrangian are assembled from them in
numpy (:class:`Assembly`) and handed to ``nlpsol`` as CasADi callbacks that write into CasADi's
own buffers: for blocks of calibration parameters through a constant sparse matrix; for blocks
that touch per-sample motion states stage by stage (:class:`Stages`). No expression graph grows
with the data, and the data themselves stay in numpy: build time, time per iteration and memory
grow linearly with the number of instances. (Differentiating one monolithic expression graph,
CasADi's default, colours a Hessian with a dense border and grows about quadratically; mapping the
local functions inside one MX graph grew CasADi's work arrays past 6 GB at 32 IMUs x 20 000
samples.) ``Solver.symbolic_nlp`` gives the same problem as one graph, as a reference.

By default (``SolverOptions.elimination = "motion"``) IPOPT sees only the calibration parameters:
the per-sample motion and the per-pose directions are eliminated exactly at every iterate
(variable projection, :mod:`castimate.solver.elimination`), with the reduced gradient and the exact
reduced Hessian (the Schur complement of the full Hessian) from the implicit function theorem; the
per-sample work is block diagonal or block banded, so nothing dense grows with the samples. The
full NLP above (``elimination = "none"``) is kept as the reference.

Uncertainty comes from the Fisher information J^T J at the solution, assembled the same way from
the local Jacobians and restricted to the tangent space of the constraints; its inverse's blocks
for the calibration parameters are the marginals with the nuisance variables (the motion)
eliminated stage-blocked.
"""

from ..problem.graph import FactorBlock, LeastSquaresProblem, Solution, SolverOptions
from .ipopt import Solver

__all__ = ["FactorBlock", "LeastSquaresProblem", "Solution", "Solver", "SolverOptions"]

"""The vectorised Cholesky factor and triangular inverse of the block-diagonal stage Hessian
(elimination._cholesky, elimination._lower_inverse)."""

import numpy as np
import pytest

from castimate.solver.elimination import _cholesky, _lower_inverse


def _cholesky_inverse(B):
    return _lower_inverse(_cholesky(B))


@pytest.mark.parametrize("m", [1, 3, 9, 12])
def test_inverse_of_the_cholesky_factor(m):
    rng = np.random.default_rng(m)
    A = rng.standard_normal((40, m, m))
    B = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(m)
    X = _cholesky_inverse(B)
    # lower triangular with a positive diagonal, and X B X^T = I (so X = L^-1 of B's Cholesky factor)
    assert (np.triu(X, 1) == 0).all() and (np.einsum("rii->ri", X) > 0).all()
    np.testing.assert_allclose(X @ B @ X.transpose(0, 2, 1), np.broadcast_to(np.eye(m), B.shape), atol=1e-12)
    np.testing.assert_allclose(X, np.linalg.inv(np.linalg.cholesky(B)), rtol=0, atol=1e-12 * np.abs(X).max())
    np.testing.assert_allclose(_cholesky(B).transpose(2, 0, 1), np.linalg.cholesky(B), rtol=0, atol=1e-12 * np.abs(B).max())


@pytest.mark.parametrize("bad", ["indefinite", "nan"])
def test_not_positive_definite_raises(bad):
    rng = np.random.default_rng(0)
    A = rng.standard_normal((10, 4, 4))
    B = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(4)
    B[7, 2, 2] = -5.0 if bad == "indefinite" else np.nan
    with pytest.raises(np.linalg.LinAlgError):
        _cholesky_inverse(B)

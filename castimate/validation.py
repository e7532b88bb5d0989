"""The one validation style for user-facing input: small checks that raise a one-line
:class:`~castimate.errors.InputError` naming the file, the key path, what was expected and what
was found. Problem files, scenario files, detection options and unit declarations use it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError


class Check:
    """Small validators that raise one-line InputErrors naming the file and key path."""

    def __init__(self, source: Path):
        self.source = source

    def fail(self, where: str, msg: str):
        raise InputError(self.source, where, msg)

    def mapping(self, v, where, allowed, required=()):
        if v is None:
            v = {}
        if not isinstance(v, dict):
            self.fail(where, f"expected a mapping, found {type(v).__name__} {v!r}")
        for k in v:
            if k not in allowed:
                self.fail(f"{where}.{k}" if where else str(k),
                          f"unknown key; expected one of {', '.join(sorted(map(str, allowed)))}")
        for k in required:
            if k not in v:
                self.fail(where or "(top level)", f"missing required key {k!r}")
        return v

    def number(self, v, where, positive=False, integer=False):
        ok = isinstance(v, (int, float)) and not isinstance(v, bool)
        if not ok or not np.isfinite(v) or (positive and v <= 0) or (integer and int(v) != v):
            kind = "a positive " if positive else "an " if integer else "a "
            kind += "integer" if integer else "finite number"
            self.fail(where, f"expected {kind}, found {v!r}")
        return int(v) if integer else float(v)

    def choice(self, v, where, options):
        if v not in options:
            self.fail(where, f"expected one of {', '.join(options)}, found {v!r}")
        return v

    def vector(self, v, where, n, kind=float):
        """A scalar (broadcast) or a list of exactly n values."""
        items = v if isinstance(v, list) else [v] * n
        if len(items) != n:
            self.fail(where, f"expected a scalar or a list of {n} values, found a list of {len(items)}")
        out = []
        for i, x in enumerate(items):
            w = f"{where}[{i}]" if isinstance(v, list) else where
            if kind is bool:
                if not isinstance(x, bool):
                    self.fail(w, f"expected true or false, found {x!r}")
                out.append(x)
            else:
                out.append(self.number(x, w))
        return tuple(out)

    def matrix3(self, v, where):
        a = np.asarray(v, dtype=object)
        if a.shape != (3, 3):
            self.fail(where, f"expected a 3x3 matrix (list of 3 rows), found shape {a.shape}")
        m = np.array([[self.number(a[i, j], f"{where}[{i}][{j}]") for j in range(3)] for i in range(3)])
        if not np.allclose(m @ m.T, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
            self.fail(where, "expected a proper rotation matrix (orthonormal, det +1)")
        return m

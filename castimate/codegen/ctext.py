"""Shared pieces of the emitted C: literals, comments, and CasADi's generated sources as text."""

from __future__ import annotations

import tempfile
from pathlib import Path

#: CasADi CodeGenerator options of every emitted file: C99 types, prefixed internals, no main.
CG_OPTIONS = {"with_header": True, "prefix": "castimate_cg_", "casadi_real": "double",
              "casadi_int": "long long int", "main": False, "mex": False, "verbose": False}


def c_comment(text: str) -> str:
    """Safe inside a C block comment, ASCII only."""
    return text.encode("ascii", "replace").decode().replace("*/", "* /")


def c_string(text: str) -> str:
    """A C string literal, ASCII only (no trigraphs)."""
    s = text.encode("ascii", "replace").decode()
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"').replace("?", "\\?") + '"'


def c_double(x: float) -> str:
    """A double that round-trips exactly in C."""
    s = repr(float(x) + 0.0)  # + 0.0: no "-0.0"
    return s if ("e" in s or "." in s or "inf" in s or "nan" in s) else s + ".0"


def casadi_sources(functions, c_name: str, **options) -> tuple[str, str]:
    """CasADi's generated C file and header of ``functions`` (named ``c_name`` and its .h), as text;
    ``options`` override :data:`CG_OPTIONS` (e.g. ``casadi_real="float"`` with its own ``prefix``)."""
    import casadi as ca

    h_name = c_name[:-2] + ".h"
    with tempfile.TemporaryDirectory(prefix="castimate-codegen-") as tmp:
        cg = ca.CodeGenerator(c_name, {**CG_OPTIONS, **options})
        for f in functions:
            cg.add(f)
        cg.generate(tmp + "/")
        c_text, h_text = Path(tmp, c_name).read_text(), Path(tmp, h_name).read_text()
    # CasADi leaves the header without a final newline.
    return (c_text if c_text.endswith("\n") else c_text + "\n"), (h_text if h_text.endswith("\n") else h_text + "\n")

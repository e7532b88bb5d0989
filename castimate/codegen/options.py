"""What ``castimate codegen`` emits, with documented defaults (the counterpart of
:class:`castimate.problem.graph.SolverOptions` for code generation)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..validation import Check

#: Default window of a dynamic problem's C solver (samples from the start of its time range).
DEFAULT_WINDOW = 200


@dataclass(frozen=True)
class CodegenOptions:
    """Options of the emitted C code.

    Attributes
    ----------
    window
        Dynamic problems: samples per solve, the size the C solver is built for (``None``: the
        default, :data:`DEFAULT_WINDOW` = 200). The static solver is built for all its poses.
    start
        Dynamic problems: first sample of the test window (default 0).
    motion_only
        Dynamic problems: the array motion estimator (ω, ω̇, s per sample; intrinsics and
        positions fixed at the problem's values, passed at run time as the fixed values). Default
        off: the calibration solver.

    They apply to a problem file of the dynamic kind only; :meth:`check` refuses them elsewhere. The
    solvers are emitted in double precision; the compensation function of a results.json in double
    and float (:mod:`castimate.codegen.compensation`).

    >>> CodegenOptions(window=60, start=100).window_or_default
    60
    >>> CodegenOptions().window_or_default
    200
    """

    window: int | None = None
    start: int = 0
    motion_only: bool = False

    @property
    def window_or_default(self) -> int:
        return DEFAULT_WINDOW if self.window is None else self.window

    @property
    def dynamic_only(self) -> bool:
        """Whether any option that only a dynamic problem's solver takes is set."""
        return self.window is not None or bool(self.start) or self.motion_only

    def check(self, source: str | Path, kind: str | None) -> "CodegenOptions":
        """Validate for a source of ``kind`` (``None``: a results.json). Raises InputError."""
        c = Check(Path(source))
        if self.window is not None:
            c.number(self.window, "--window", positive=True, integer=True)
        c.number(self.start, "--start", integer=True)
        if self.start < 0:
            c.fail("--start", f"expected a sample index >= 0, found {self.start}")
        if self.dynamic_only and kind is None:
            c.fail("", "--window, --start and --motion-only apply to a problem file, not a results file")
        if self.dynamic_only and kind is not None and kind != "dynamic_array":
            c.fail("kind", f"--window, --start and --motion-only apply to dynamic_array problems, found {kind} "
                           "(emitted for all its poses)")
        return self


__all__ = ["CodegenOptions", "DEFAULT_WINDOW"]

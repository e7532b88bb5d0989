"""The pipelines, one module per kind of problem, behind one protocol (:class:`Kind`).

Every kind goes through the same steps, and everything above this package (the CLI, diagnose,
the outputs, codegen's reference solves, the Python API) uses only these:

    kind = kind_of(spec)                    # the registered Kind of spec.kind
    data = kind.load(spec, log)             # read and prepare the session once
    config = kind.configure(spec, data)     # the triads and the model structure for these data
    problem = kind.build(config, data)      # the factor graph (problem.lsq)
    kind.check(spec, problem, solver, data) # refuse what the data cannot determine
    outcome = kind.calibrate(spec, data, log)  # all of the above, solved: the kind's outcome

A third kind is a new module with a class implementing :class:`Kind` and one line in
:data:`REGISTRY`. Every outcome has ``spec``, ``config``, ``problem``, ``solver``, ``solution``,
``calibration`` and ``gyro_calibration`` ((T, b) per triad), ``residual_acc`` and ``residual_gyro``.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np

from ..errors import InputError
from ..spec import ProblemSpec

Log = Callable[[str], None]

#: spec.kind -> module of castimate.kinds whose ``KIND`` implements :class:`Kind`.
REGISTRY = {"static_array": "static", "dynamic_array": "dynamic", "ferraris": "ferraris"}

#: sensor -> triad -> (residual (n, 3), σ (n, 3)) in physical units
Residuals = dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]


def quiet(msg: str) -> None:
    """A Log that says nothing."""


@dataclass(frozen=True)
class CrossValidation:
    """Prediction error on held-out data: fit on the other folds, fix the calibration (and
    geometry), estimate only the held-out nuisance variables (pose directions or motion), and take
    the residual.

    A fold whose fit or prediction did not converge is left out of the RMS and named in ``failed``;
    ``fold_ss`` and ``fold_n`` (per fold: the sum of squared whitened held-out residuals and their
    count, NaN and 0 for a failed fold) let two models be compared on the folds both predicted
    (:meth:`rms_over`)."""

    folds: int
    rms: float  # whitened residual RMS, all sensors (1 for a perfect model and honest σ)
    rms_acc: float  # m/s^2
    rms_gyro: float  # rad/s, nan without gyroscopes
    fold_ss: tuple[float, ...] = ()
    fold_n: tuple[int, ...] = ()
    failed: tuple[str, ...] = ()  # "fold k of K: what did not converge"

    @classmethod
    def from_parts(cls, white: list, acc: list, gyro: list, folds: int, fold_of: list[int] | None = None,
                   failed: tuple[str, ...] = ()) -> "CrossValidation":
        """RMS over the held-out residual parts (NaN entries, i.e. masked samples, left out).
        ``fold_of``: the fold of each part of ``white``; ``failed``: the folds that did not converge."""
        def finite(parts):
            x = np.concatenate([np.ravel(p) for p in parts]) if parts else np.array([])
            return x[np.isfinite(x)]

        def rms(parts):
            x = finite(parts)
            return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")

        ss, n = (), ()
        if fold_of is not None:
            per = [finite([w for w, f in zip(white, fold_of) if f == k]) for k in range(folds)]
            ss = tuple(float(x @ x) if x.size else float("nan") for x in per)
            n = tuple(int(x.size) for x in per)
        return cls(folds, rms(white), rms(acc), rms(gyro), ss, n, tuple(failed))

    @property
    def predicted(self) -> np.ndarray:
        """(folds,) whether each fold was fitted and predicted (all, without per-fold figures)."""
        if not self.fold_n:
            return np.full(self.folds, not self.failed)
        return np.array([k > 0 and np.isfinite(s) for s, k in zip(self.fold_ss, self.fold_n)])

    def rms_over(self, folds: np.ndarray) -> float:
        """Whitened held-out RMS over the folds marked in ``folds`` (all predicted folds: :attr:`rms`)."""
        folds = np.asarray(folds, bool)
        if not self.fold_n or folds.all() and self.predicted.all():
            return self.rms
        n = sum(k for k, f in zip(self.fold_n, folds) if f)
        return float(np.sqrt(sum(s for s, f in zip(self.fold_ss, folds) if f) / n)) if n else float("nan")


class Kind(Protocol):
    """One kind of problem (``spec.kind``): how its data are read, modelled, solved and checked."""

    name: str  # the spec.kind it serves
    warm_start: bool  # calibrate and cross_validate start from ``start`` (else they ignore it)
    sampled: bool  # the data are a time series (windows of samples), not a set of poses

    def load(self, spec: ProblemSpec, log: Log = quiet) -> Any:
        """Read the recording and prepare it (poses, masks, noise) once; every model variant of the
        session is fitted to it."""

    def configure(self, spec: ProblemSpec, data: Any, log: Log = quiet) -> Any:
        """The problem structure (triads, settings, regressors) of ``spec``'s model for these data."""

    def build(self, config: Any, data: Any, fixed_size: bool = False) -> Any:
        """The factor graph (``.lsq``, ``.calibration(values)``, ``.gyro_triads``). ``fixed_size``:
        a structure that does not depend on which readings are masked (for the C solver)."""

    def check(self, spec: ProblemSpec, problem: Any, solver: Any, data: Any) -> None:
        """Raise InputError if the data cannot determine the problem (before solving)."""

    def calibrate(self, spec: ProblemSpec, data: Any, log: Log = quiet, quick: bool = False, start: Any = None) -> Any:
        """Configure, build, check and solve: the kind's outcome. Raises InputError or
        NotConvergedError. ``quick``: only the fit, without the figures of merit that need extra
        solves (static: the single-triad consistency of Nilsson's sec. IV)."""

    def nuisance_only(self, config: Any) -> Any:
        """The same structure with every calibration and geometry group fixed at its start value:
        the estimator of the nuisance variables (pose directions, motion) alone."""

    def settled(self, config: Any, outcome: Any) -> Any:
        """The configuration with the settings an outcome estimated besides its parameters (the
        dynamic kind's process-noise levels), so that a problem built from it has the outcome's
        solution as its optimum (diagnose's score tests)."""

    def window(self, spec: ProblemSpec, data: Any, start: int, n: int) -> tuple[Any, str]:
        """The data restricted to n consecutive samples or poses from ``start``, and a note of which."""

    def describe(self, config: Any, data: Any, problem: Any) -> str:
        """One line naming the model and the size of the problem."""

    def has_temperature(self, data: Any) -> bool:
        """Whether the data log a temperature (temperature effects can be informed)."""

    def cross_validate(self, spec: ProblemSpec, data: Any, folds: int, start: Any = None,
                       log: Log = quiet) -> CrossValidation:
        """K-fold prediction error of ``spec``'s model on these data.

        ``start`` (here and in ``calibrate``): an outcome of the same session to start the fits
        from instead of the nominal values (diagnose's refits); a kind whose ``warm_start`` is false
        ignores it. ``log`` names the folds that did not converge."""

    def residuals(self, outcome: Any) -> tuple[np.ndarray, Residuals]:
        """Times (pose mid-times or samples) and the residuals with their σ per sensor and triad."""


def kind_of(spec: ProblemSpec | str) -> Kind:
    """The registered :class:`Kind` of a problem (or of a kind's name)."""
    name = spec if isinstance(spec, str) else spec.kind
    if name not in REGISTRY:
        raise InputError(getattr(spec, "path", ""), "kind", f"expected one of {', '.join(REGISTRY)}, found {name!r}")
    return importlib.import_module(f"{__name__}.{REGISTRY[name]}").KIND


def calibrate(spec: ProblemSpec, log: Log | None = None):
    """Read, configure, build, check and solve a problem: the outcome of its kind."""
    kind = kind_of(spec)
    log = log or quiet
    return kind.calibrate(spec, kind.load(spec, log), log)

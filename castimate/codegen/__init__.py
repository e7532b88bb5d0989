"""C code generation (``castimate codegen``).

- From a ``results.json``: the compensation function of a calibration (:mod:`.compensation`).
- From a problem file: a C solver of the problem, so a device can recalibrate without Python
  (:mod:`.solvers`, :mod:`.gn_structure`, the driver ``c/castimate_gn.c``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..errors import InputError
from ..io.atomic import write_atomic
from .compensation import generate_files, load_calibration
from .options import CodegenOptions


def is_problem_file(path: str | Path) -> bool:
    """A problem file by its name (.yaml, .yml); anything else is read as a results.json."""
    return Path(path).suffix.lower() in (".yaml", ".yml")


def codegen_io(source: str | Path) -> tuple[tuple, tuple[str, ...]]:
    """(the files codegen of ``source`` reads, the names it writes into its directory), for the
    output check before any work: a problem file reads its data, gyroscope file, sections and
    intrinsics too, and none of them may be replaced by a generated file."""
    if is_problem_file(source):
        from ..spec import load_problem
        from .solvers import FILES

        return load_problem(source).inputs, FILES
    from .compensation import FILES

    return (source,), FILES


def generate_c(source: str | Path, out_dir: str | Path, options: CodegenOptions = CodegenOptions(),
               log: Callable[[str], None] = lambda m: None) -> dict[str, Path]:
    """Write C sources, header, test vectors, test program, Makefile and README into out_dir.

    ``source`` is a results.json (the compensation function) or a problem file (its solver, see
    :class:`CodegenOptions` for the window of a dynamic problem and the motion estimator). Returns
    {name: path} of the files written. Raises InputError for bad input, NotConvergedError if the
    reference solve fails. ``log``: progress lines.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(out_dir, "", "expected an output directory, found a file")
    if is_problem_file(source):
        from .solvers import generate_solver_files, reference_for

        ref = reference_for(source, options, log)
        log("generating the C solver (CasADi)")
        files = generate_solver_files(ref)
    else:
        options.check(source, None)
        files = generate_files(source)
        log(f"generated the compensation function of {Path(source).name} (CasADi)")
    written = {}
    for name, text in files.items():
        write_atomic(out_dir / name, text)
        written[name] = out_dir / name
    return written


__all__ = ["CodegenOptions", "codegen_io", "generate_c", "generate_files", "is_problem_file", "load_calibration"]

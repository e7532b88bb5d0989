"""C code generation (``castimate codegen``): the compensation function of a calibration as plain C99."""

from .compensation import generate_c, generate_files, load_calibration

__all__ = ["generate_c", "generate_files", "load_calibration"]

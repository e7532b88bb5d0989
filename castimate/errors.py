"""Errors that the CLI maps to exit codes.

Every user-facing error is one line: the file, the YAML key path or data column, what was
expected and what was found.
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_INVALID_INPUT = 2
EXIT_NOT_CONVERGED = 3
EXIT_PARTIAL = 4  # castimate batch: some recordings failed (each reported; the others' results written)


class CastimateError(Exception):
    """Base class for errors reported to the user on one line."""

    exit_code = 1


class InputError(CastimateError, ValueError):
    """Invalid input: a problem file, a data file or a command-line argument.

    Parameters
    ----------
    source
        The file (or other origin) the bad input came from.
    where
        The YAML key path (``model.accelerometer.gain``) or data column (``imu1.ax``);
        empty if the whole file is at fault.
    message
        What was expected and what was found.
    """

    exit_code = EXIT_INVALID_INPUT

    def __init__(self, source: object, where: str, message: str):
        self.source = str(source)
        self.where = where
        self.message = message
        loc = f"{self.source}: {where}: " if where else f"{self.source}: "
        super().__init__((loc + message).replace("\n", " "))


class NotConvergedError(CastimateError):
    """The solver stopped without meeting its convergence criteria."""

    exit_code = EXIT_NOT_CONVERGED

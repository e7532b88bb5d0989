"""castimate: maximum-likelihood calibration of inertial sensor arrays.

The public Python surface is :mod:`castimate.api`, available as ``castimate.load``,
``castimate.solve``, ``castimate.write``, ``castimate.diagnose``, ``castimate.Calibration`` (loaded on first use, so that
``import castimate`` stays light and the CLI can set up numpy's threads first). The numerical
solver is the subpackage :mod:`castimate.solver`.
"""

from .version import __version__ as __version__  # re-exported (not in __all__, which is the API of castimate.api)

__all__ = ["Calibration", "InputError", "NotConvergedError", "ProblemSpec", "diagnose", "load", "solve", "write"]


def __getattr__(name: str):
    if name in __all__:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'castimate' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The module's names and the lazy API's (tab completion lists castimate.solve before its first use)."""
    return sorted({*globals(), *__all__})

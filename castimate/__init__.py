"""castimate: maximum-likelihood calibration of inertial sensor arrays.

The public Python surface is :mod:`castimate.api`, available as ``castimate.load``,
``castimate.solve``, ``castimate.write``, ``castimate.diagnose``, ``castimate.Calibration`` (loaded on first use, so that
``import castimate`` stays light and the CLI can set up numpy's threads first).
"""

import sys
import types

from .version import __version__
__all__ = ["Calibration", "InputError", "NotConvergedError", "ProblemSpec", "diagnose", "load", "solve", "write"]


def __getattr__(name: str):
    if name in __all__:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'castimate' has no attribute {name!r}")


class _Package(types.ModuleType):
    """The package keeps its API names: importing the subpackage ``castimate.solve`` (the solver)
    would otherwise make ``castimate.solve`` that module instead of :func:`castimate.api.solve`
    (the import system sets a package's attribute to each submodule it loads)."""

    def __setattr__(self, name: str, value) -> None:
        if name in __all__ and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package

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


class _SolvePackage(types.ModuleType):
    """``castimate.solve`` is both the solver subpackage (``castimate.solve.Solver``, its modules) and
    the API function: calling it calls :func:`castimate.api.solve`."""

    def __call__(self, *args, **kwargs):
        from .api import solve

        return solve(*args, **kwargs)


class _Package(types.ModuleType):
    """The import system sets a package's attribute to each submodule it loads, so importing the
    subpackage ``castimate.solve`` would hide the API function of the same name: the subpackage is
    made callable instead (:class:`_SolvePackage`)."""

    def __setattr__(self, name: str, value) -> None:
        if name == "solve" and type(value) is types.ModuleType:
            value.__class__ = _SolvePackage
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package

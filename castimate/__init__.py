"""castimate: maximum-likelihood calibration of inertial sensor arrays.

The math lives in :mod:`castimate.models` (symbolic physics) and :mod:`castimate.problem`
(problem assembly); :mod:`castimate.solve` is the one solve path shared by every kind.
IO, the CLI and reporting are kept apart from both.
"""

__version__ = "0.1.0"

"""Whether the model fits the data: one verdict for the terminal summary, results.json and the report.

A solver that converged is not yet a calibration that holds: where the residuals are many times the
noise model's σ, or nearly deterministic, the model lacks an effect and the estimates carry its error,
however IPOPT ended. Two tests, both from the fit itself:

- χ²/dof above :data:`NO_FIT`: the residuals are about √(χ²/dof) times the σ's of the noise model;
- the whitened residuals' lag-1 autocorrelation (the dynamic kind's HAC σ's compute it), median over
  the triads' sensors, above :data:`MISFIT_AUTOCORRELATION`: a misfit that χ²/dof no longer shows
  once the motion-dependent noise model has fitted σ's to it.
"""

from __future__ import annotations

import math

import numpy as np

#: A model whose χ²/dof is above this is reported as not fitting, however the solver ended (the
#: residuals are then about √(χ²/dof) times the noise model's σ).
NO_FIT = 4.0

#: Whitened residuals whose lag-1 autocorrelation, median over the triads' sensors, exceeds this are
#: mostly deterministic: a misfit of the model that χ²/dof hides once the motion-dependent noise model
#: has fitted σ's to it (χ²/dof 1.00–1.01 in every case below). Independent noise gives 0; pink noise
#: as large as the white, with every effect modelled (the messy board of
#: problems/montecarlo_messy_8x1000.yaml, 7 seeds): 0.38–0.40; the same sessions solved with the
#: problem simulate writes, which lacks their clock beat, delay and gyroscope coupling: 0.78–0.94; the
#: five real MIMU4444 sessions as declared: 0.20–0.23, after diagnose 0.01–0.08; a gyro-free board
#: with positions fixed 1 mm off: 0.98 (0.06 at the true positions).
MISFIT_AUTOCORRELATION = 0.7


def misfit_warning(lag1: dict) -> str | None:
    """The sentence that says the model does not fit, from the residuals' lag-1 autocorrelation per
    sensor and triad (results.json's ``uncertainty.lag1_autocorrelation``), or None."""
    rho = [v for c in lag1.values() for v in c.values() if np.isfinite(v)]
    if not rho or np.median(rho) <= MISFIT_AUTOCORRELATION:
        return None
    return (f"the model does not fit: the residuals' lag-1 autocorrelation is {np.median(rho):.2f} (median over "
            f"the triads' sensors; independent noise gives 0, above {MISFIT_AUTOCORRELATION} they are nearly "
            f"deterministic), a "
            f"misfit that χ²/dof does not show once the noise model has fitted σ's to it; the estimates carry "
            f"unmodelled errors (try castimate diagnose)")


def fit_verdict(success: bool, message: str, chi2_per_dof: float | None, dof: float | None,
                lag1: dict | None = None) -> tuple[str, str]:
    """(level, sentence) on whether the model fits the data, from the solver's status, χ²/dof over
    ``dof`` degrees of freedom and the residuals' lag-1 autocorrelation (:func:`misfit_warning`).
    ``level``: "bad" (the solver did not converge, or the model does not fit), "warn" (it converged
    and the fit cannot be judged, or χ²/dof is above 1 by more than its 99 % band, 2.58 √(2/dof),
    up to :data:`NO_FIT`) or "ok"."""
    def finite(x):
        return x is not None and math.isfinite(x)

    if not success:
        return "bad", f"The solver did not converge ({message}): the estimates are not valid."
    if not finite(chi2_per_dof):
        return "warn", "The solver converged; the fit cannot be judged (no χ²/dof)."
    chi2 = chi2_per_dof
    if chi2 > NO_FIT:
        return "bad", (f"The model does not fit the data: χ²/dof = {chi2:.4g}, the residuals are about "
                       f"{math.sqrt(chi2):.3g} × the noise σ. The solver converged, but the estimates and their σ's "
                       "carry unmodelled errors (try castimate diagnose).")
    misfit = misfit_warning(lag1 or {})
    if misfit:
        return "bad", f"{misfit[0].upper()}{misfit[1:]} (χ²/dof = {chi2:.3g})."
    band = 2.58 * math.sqrt(2 / dof) if finite(dof) and dof > 0 else 0.0
    if chi2 > 1 + band:
        return "warn", (f"The model fits approximately: χ²/dof = {chi2:.3g}, the residuals exceed the noise model "
                        f"(σ's about {math.sqrt(chi2):.2g} × too small for the σ's reported).")
    return "ok", f"The model fits the data: χ²/dof = {chi2:.3g}, within the noise model."

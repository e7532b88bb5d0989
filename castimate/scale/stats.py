"""The arithmetic of batches, Monte Carlo studies and plans, on plain documents: no IO, no Dask.

Parameters are compared by label, ``<triad>.<sensor>.<group>[<component>]`` (``imu2.accelerometer.gain[x]``, ``imu2.accelerometer.nonorthogonality[yx]``: as the solver's layout
labels them)
or ``<triad>.position[<component>]``, the same for an estimate (a results.json document) and a truth
(a truth.json document of ``castimate simulate``). Only free components are labelled.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..problem.effects import BY_KEY
from ..problem.triads import SENSOR_GROUPS


@dataclass(frozen=True)
class Estimate:
    value: float
    std: float
    unit: str


def _components(x) -> list:
    return list(np.ravel(np.asarray(x, float)))


def components(group: str, n: int) -> tuple[str, ...]:
    """The names of the n components of a group (``accelerometer.nonorthogonality``: yx, zx, zy),
    as the solver's layout labels them; x, y, z or indices for a group the registry does not know."""
    sensor, _, name = group.partition(".")
    gd = SENSOR_GROUPS.get(sensor, {}).get(name) or (BY_KEY[group].group if group in BY_KEY else None)
    if gd is not None and len(gd.components) == n:
        return tuple(gd.components)
    return tuple("xyz") if n == 3 else tuple(str(i) for i in range(n))


#: Parameter groups of a triad that belong to no sensor (results.json names the others' accelerometer
#: groups without a prefix: ``gain`` is ``accelerometer.gain``).
GEOMETRY = ("position",)


def estimates(results: dict) -> dict[str, Estimate]:
    """Label -> estimate and σ of every free parameter component of a results.json document (the
    σ of the white-noise model, not scaled by χ²/dof)."""
    out: dict[str, Estimate] = {}
    for triad, t in results.get("triads", {}).items():
        for key, p in t.get("parameters", {}).items():
            group = key if key.startswith(("accelerometer.", "gyroscope.")) or key in GEOMETRY else f"accelerometer.{key}"
            values = _components(p["value"])
            free = _components(p.get("free", [True] * len(values)))
            names = p.get("components") or components(group, len(values))
            for c, v, s, f in zip(names, values, _components(p["std"]), free):
                if f:
                    out[f"{triad}.{group}[{c}]"] = Estimate(v, s, str(p.get("unit", "")))
    return out


def truth_values(truth: dict) -> dict[str, float]:
    """Label -> true value of every parameter component a truth.json document states."""
    out: dict[str, float] = {}
    for triad, t in truth.get("triads", {}).items():
        for key, v in t.get("parameters", {}).items():
            values = _components(v)
            for c, x in zip(components(key, len(values)), values):
                out[f"{triad}.{key}[{c}]"] = x
        if "position" in t and "parameters" not in t:  # dynamic scenarios: positions from the reference
            for c, x in zip("xyz", _components(t["position"])):
                out[f"{triad}.position[{c}]"] = x
    return out


def errors_over_sigma(results: dict, truth: dict) -> dict[str, float]:
    """Label -> (estimate - truth) / σ of every free parameter component that truth.json states."""
    true = truth_values(truth)
    return {lab: (e.value - true[lab]) / e.std for lab, e in estimates(results).items() if lab in true and e.std > 0}


def group_of(label: str) -> str:
    """The parameter group of a label without triad and component: ``accelerometer.gain``."""
    return label.split(".", 1)[1].split("[")[0]


# ---------------------------------------------------------------------------------------------
# Batches: the spread of many units or sessions against their σ's
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ParameterSpread:
    """One parameter over the recordings of a batch."""

    label: str
    unit: str
    median: float
    spread: float  # sample std over the recordings (NaN for one)
    sigma: float  # median reported σ
    z: dict[str, float]  # recording -> (x - median) / σ of that recording
    sigma_scaled: float = float("nan")  # median σ scaled by the recording's sqrt(χ²/dof)

    @property
    def spread_over_sigma(self) -> float:
        return self.spread / self.sigma if self.sigma > 0 else float("inf")

    def outliers(self, threshold: float) -> dict[str, float]:
        return {n: z for n, z in self.z.items() if abs(z) > threshold}


def batch_spread(params: dict[str, dict[str, Estimate]], chi2_per_dof: dict[str, float] | None = None
                 ) -> list[ParameterSpread]:
    """Per parameter of any recording (recording -> label -> estimate): median, spread and the
    distance of every recording from the median in its own σ's; with the recordings' χ²/dof, also
    the median σ scaled by sqrt(χ²/dof) (the σ if the misfit were white noise)."""
    scale = {n: np.sqrt(max(chi2_per_dof.get(n, np.nan), 0.0)) if chi2_per_dof else np.nan for n in params}
    labels = list(dict.fromkeys(lab for p in params.values() for lab in p))
    out = []
    for lab in labels:
        have = {n: p[lab] for n, p in params.items() if lab in p}
        x = np.array([e.value for e in have.values()])
        s = np.array([e.std for e in have.values()])
        med = float(np.median(x))
        spread = float(np.std(x, ddof=1)) if len(x) > 1 else float("nan")
        z = {n: (e.value - med) / e.std if e.std > 0 else float("inf") * np.sign(e.value - med)
             for n, e in have.items()}
        scaled = float(np.median([e.std * scale[n] for n, e in have.items()]))
        out.append(ParameterSpread(lab, next(iter(have.values())).unit, med, spread, float(np.median(s)), z, scaled))
    return out


# ---------------------------------------------------------------------------------------------
# Monte Carlo: errors against the truth, σ honesty and efficiency
# ---------------------------------------------------------------------------------------------

def sampling_band(runs: int, k: float = 3.0) -> float:
    """Half-width of the k-standard-error band of a sample RMS or std of ``runs`` standard-normal
    draws around 1: the standard error is about 1/sqrt(2 runs)."""
    return k / np.sqrt(2 * max(runs, 1))


@dataclass
class MonteCarloResult:
    """Per calibration parameter (columns) and successful run (rows)."""

    labels: list[str]
    errors: np.ndarray  # estimate - truth, physical units
    z: np.ndarray  # error / reported σ of that run
    crb: np.ndarray  # the bound's σ (Cramér-Rao bound of the study's named bound)
    failures: int  # runs that did not converge or were refused (excluded)
    sigma: np.ndarray | None = None  # the σ each run reported (same shape as errors)

    @property
    def z_std(self) -> np.ndarray:
        return self.z.std(axis=0, ddof=1)

    @property
    def rmse_over_crb(self) -> np.ndarray:
        return np.sqrt((self.errors ** 2).mean(axis=0)) / self.crb


def score_runs(truth: dict[str, float], crb: dict[str, float], runs: list[dict[str, Estimate]],
               failures: int) -> MonteCarloResult:
    """Errors, error/σ and the CRB of every parameter the truth, the bound and every run share."""
    labels = [lab for lab in crb if lab in truth and all(lab in r for r in runs)]
    errors = np.array([[r[lab].value - truth[lab] for lab in labels] for r in runs]).reshape(len(runs), len(labels))
    sig = np.array([[r[lab].std for lab in labels] for r in runs]).reshape(len(runs), len(labels))
    with np.errstate(divide="ignore", invalid="ignore"):
        z = errors / sig
    return MonteCarloResult(labels, errors, z, np.array([crb[lab] for lab in labels]), failures, sig)


def pooled_score(sc: MonteCarloResult, select: list[str] | None = None,
                 correlation: tuple[list[str], np.ndarray] | None = None) -> dict:
    """Statistics pooled over the runs and the parameters ``select`` (default all) of a study, with
    their standard errors for Gaussian errors e ~ N(0, C), C the bound's covariance (``correlation``:
    labels and the bound's correlation matrix ρ; None: independent parameters).

    Over P parameters and R runs, the pooled ratio sqrt(mean e²) / sqrt(mean diag C) has standard
    error sqrt(tr C² / 2) / (tr C sqrt(R)); the pooled std of e / σ_bound has sqrt(tr ρ² / 2) / (P sqrt(R))
    and the pooled mean sqrt(Σρ) / (P sqrt(R)). Without correlation both first are 1/sqrt(2RP)."""
    cols = [j for j, lab in enumerate(sc.labels) if select is None or lab in select]
    labels = [sc.labels[j] for j in cols]
    E, Z, crb = sc.errors[:, cols], sc.z[:, cols], sc.crb[cols]
    R, P = E.shape
    if correlation is not None:
        idx = {lab: i for i, lab in enumerate(correlation[0])}
        missing = [lab for lab in labels if lab not in idx]
        if missing:
            raise ValueError(f"the bound's correlation lacks {missing[:3]}")
        k = [idx[lab] for lab in labels]
        rho = np.asarray(correlation[1], float)[np.ix_(k, k)]
    else:
        rho = np.eye(P)
    C = rho * np.outer(crb, crb)
    out = {"parameters": P, "runs": R, "crb_rms": float(np.sqrt(np.mean(crb ** 2)))}
    if R == 0:
        return out
    rmse = float(np.sqrt(np.mean(E ** 2)))
    Zc = E / crb
    out.update({
        "rmse": rmse, "rmse_over_crb": rmse / out["crb_rms"],
        "rmse_over_crb_se": float(np.sqrt(np.trace(C @ C) / 2) / np.trace(C) / np.sqrt(R)),
        "z_crb_std": float(Zc.std(ddof=1)) if Zc.size > 1 else float("nan"), "z_crb_mean": float(Zc.mean()),
        "z_std_se": float(np.sqrt(np.trace(rho @ rho) / 2) / P / np.sqrt(R)),
        "z_mean_se": float(np.sqrt(max(rho.sum(), 0.0)) / P / np.sqrt(R)),
        "z_reported_std": float(Z.std(ddof=1)) if Z.size > 1 else float("nan"), "z_reported_mean": float(Z.mean()),
    })
    if sc.sigma is not None:
        S = sc.sigma[:, cols]
        out["reported_sigma_rms"] = float(np.sqrt(np.mean(S ** 2)))
        out["reported_sigma_over_crb_median"] = float(np.median(S / crb))
    return out


def montecarlo_table(sc: MonteCarloResult, truth: dict[str, float]) -> list[dict]:
    """One row per parameter: truth, CRB, RMSE, RMSE/CRB, mean and std of error/σ (NaN where the
    runs are too few)."""
    n = len(sc.errors)
    mean_z = sc.z.mean(axis=0) if n else np.full(len(sc.labels), np.nan)
    return [{"parameter": lab, "truth": truth[lab], "crb": float(sc.crb[j]),
             "rmse": float(np.sqrt(np.mean(sc.errors[:, j] ** 2))) if n else float("nan"),
             "rmse_over_crb": float(sc.rmse_over_crb[j]) if n else float("nan"),
             "mean_z": float(mean_z[j]), "std_z": float(sc.z_std[j]) if n > 1 else float("nan")}
            for j, lab in enumerate(sc.labels)]


# ---------------------------------------------------------------------------------------------
# Plans: the Cramér-Rao bound against the duration of the protocol
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PlanCase:
    """The bound of one protocol length: label -> CRB σ (inf: undetermined)."""

    duration: float  # s
    crb: dict[str, float]
    units: dict[str, str] = field(default_factory=dict)
    undetermined: tuple[str, ...] = ()  # the undetermined directions, each named by its largest components


def crb_table(cases: list[PlanCase]) -> tuple[list[str], np.ndarray]:
    """Labels and the (durations, labels) CRB matrix (NaN where a case lacks the parameter)."""
    labels = list(dict.fromkeys(lab for c in cases for lab in c.crb))
    return labels, np.array([[c.crb.get(lab, np.nan) for lab in labels] for c in cases])


def duration_exponent(durations, crb: np.ndarray) -> np.ndarray:
    """Per column of ``crb`` (durations, labels), the exponent a of CRB ∝ duration^a fitted in
    log-log over the finite entries (-1/2 for white noise averaged longer; NaN with fewer than two)."""
    d = np.log(np.asarray(durations, float))
    out = np.full(crb.shape[1], np.nan)
    for j in range(crb.shape[1]):
        ok = np.isfinite(crb[:, j]) & (crb[:, j] > 0)
        if ok.sum() >= 2 and np.ptp(d[ok]) > 0:
            out[j] = np.polyfit(d[ok], np.log(crb[ok, j]), 1)[0]
    return out


def plan_table(cases: list[PlanCase]) -> list[dict]:
    """One row per parameter: unit, the CRB of every case (``crb_<duration>s``, inf: undetermined)
    and the exponent of its fall with duration."""
    labels, crb = crb_table(cases)
    a = duration_exponent([c.duration for c in cases], crb)
    units = {lab: u for c in cases for lab, u in c.units.items() if u}
    return [{"parameter": lab, "unit": units.get(lab, ""),
             **{f"crb_{c.duration:g}s": float(crb[i, j]) for i, c in enumerate(cases)}, "exponent": float(a[j])}
            for j, lab in enumerate(labels)]

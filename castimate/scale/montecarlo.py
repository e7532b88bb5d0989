"""``castimate montecarlo``: simulate, solve and score many noise realisations of one scenario.

The scenario's ``seed`` fixes the truth (parameters, poses or motion); run k draws its noise from
the noise seed k (:func:`castimate.simulate.scenarios.simulate_scenario`), so every run estimates
the same truth and the Cramér-Rao bound is one: the σ's of the noise-free session's solution
(:func:`solve_noise_free`, also the engine of ``castimate plan``).
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml

from ..errors import InputError
from ..kinds import kind_of
from ..output import OUTPUTS
from ..simulate.montecarlo import MonteCarloResult
from ..simulate.scenarios import simulate_scenario
from ..solver.ipopt import Solver
from ..solver.uncertainty import partial_bound
from ..spec import load_problem, motion_noise_setting
from ..validation import Check, load_yaml
from .engine import TaskResult, run_tasks
from .stats import Estimate, estimates, score_runs, truth_values

MAX_RUNS = 10 ** 6


def load_scenario(path: str | Path, drop: tuple[str, ...] = ()) -> dict:
    """A scenario file's mapping (checked fully when first simulated); ``drop``: keys of the caller's
    own (a plan's ``plan``) taken out before."""
    raw = load_yaml(path, "scenario file")
    if not isinstance(raw, dict):
        Check(Path(path)).fail("", f"expected a scenario mapping, found {type(raw).__name__}")
    if "data" in raw or "array" in raw:
        Check(Path(path)).fail("", f"this is a problem file (it has {' and '.join(k for k in ('data', 'array') if k in raw)})"
                                   ", not a scenario: expected a scenario as for `castimate simulate`")
    return {k: v for k, v in raw.items() if k not in drop}


def check_runs(runs) -> int:
    if isinstance(runs, bool) or not isinstance(runs, int) or not 2 <= runs <= MAX_RUNS:
        raise InputError("--runs", "", f"expected a number of runs from 2 to {MAX_RUNS}, found {runs!r}")
    return runs


@dataclass(frozen=True)
class Simulated:
    """One simulated session solved: the truth, the estimates with their σ's, the fit."""

    truth: dict[str, float]
    estimates: dict[str, Estimate]
    chi2_per_dof: float
    undetermined: tuple[str, ...] = ()


def _simulate(scenario: dict, source: str, tmp: Path, noise_seed: int | None, noise_free: bool):
    path = tmp / (Path(source).name if source else "scenario.yaml")
    path.write_text(yaml.safe_dump(scenario, sort_keys=False))
    try:
        files = simulate_scenario(path, tmp / "sim", noise_seed=noise_seed, noise_free=noise_free)
    except InputError as e:  # name the user's file, not the worker's copy
        raise InputError(source or e.source, e.where, e.message) from None
    return json.loads(files["truth"].read_text()), load_problem(files["problem"])


def solve_simulated(scenario: dict, noise_seed: int | None = None, noise_free: bool = False, source: str = "") -> Simulated:
    """On a worker: simulate the scenario (its truth, noise from ``noise_seed``) and solve it
    through the kind's pipeline."""
    with tempfile.TemporaryDirectory(prefix="castimate-mc-") as tmp:
        truth, spec = _simulate(scenario, source, Path(tmp), noise_seed, noise_free)
        kind = kind_of(spec)
        outcome = kind.calibrate(spec, kind.load(spec), quick=True)
        res = OUTPUTS[spec.kind].results(outcome)
    return Simulated(truth_values(truth), estimates(res), float(res["residuals"]["chi2_per_dof"]))


def solve_noise_free(scenario: dict, source: str = "") -> Simulated:
    """The scenario's session without noise, solved: its estimates are the truth and their σ's the
    Cramér-Rao bound of the scenario's noise. Directions the data cannot determine are named
    (``undetermined``) and their parameters get an infinite bound, where the pipeline would refuse."""
    with tempfile.TemporaryDirectory(prefix="castimate-crb-") as tmp:
        truth, spec = _simulate(scenario, source, Path(tmp), None, True)
        # the bound of the declared σ's: no motion-dependent noise fitted to the exact readings, and
        # the Fisher σ's (a sandwich of the exact readings' vanishing residuals would be zero)
        spec = replace(spec, noise=replace(spec.noise, motion_dependent=motion_noise_setting("none")),
                       uncertainty=replace(spec.uncertainty, residual_correlation="none"))
        kind = kind_of(spec)
        data = kind.load(spec)
        problem = kind.build(kind.configure(spec, data), data)
        solver = Solver(problem.lsq, spec.solver)
        bad = solver.undetermined(problem.lsq.layout.x0())
        if not bad:
            outcome = kind.calibrate(spec, data, quick=True)
            res = OUTPUTS[spec.kind].results(outcome)
            return Simulated(truth_values(truth), estimates(res), float(res["residuals"]["chi2_per_dof"]))
        # undetermined: solve anyway (the noise-free data are fitted exactly on a manifold of
        # solutions) and bound what is determined, on the subspace orthogonal to the null directions
        sol = solver.solve()
        labels = problem.lsq.layout.x_labels
        if sol.success:
            std, free = partial_bound(solver, sol.x)
        else:
            std, free = np.full(len(solver.theta), np.nan), np.zeros(len(solver.theta), bool)
        lay = problem.lsq.layout
        est = {labels[i]: Estimate(float("nan"), float("inf") if f else float(s), lay.group(labels[i].split("[")[0]).unit)
               for i, s, f in zip(solver.theta, std, free)}
        return Simulated(truth_values(truth), est, 0.0, tuple(bad))


@dataclass(frozen=True)
class MonteCarloStudy:
    scenario: str
    runs: int
    bound: Simulated  # the noise-free solve: truth and CRB
    results: list[TaskResult]  # per run, a Simulated
    score: MonteCarloResult

    def failures(self) -> dict[str, int]:
        """Failed runs by reason: not converged, invalid input (e.g. a refused session), other."""
        out: dict[str, int] = {}
        for r in self.results:
            if not r.ok:
                why = "not converged" if "did not converge" in r.error else \
                    "internal error" if r.error.startswith(("internal error", "the task failed")) else "refused"
                out[why] = out.get(why, 0) + 1
        return out


def score_study(scenario: str, bound: Simulated, results: list[TaskResult]) -> MonteCarloStudy:
    ok = [r.value for r in results if r.ok]
    crb = {lab: e.std for lab, e in bound.estimates.items()}
    score = score_runs(bound.truth, crb, [s.estimates for s in ok], len(results) - len(ok))
    return MonteCarloStudy(scenario, len(results), bound, results, score)


def run_montecarlo(client, scenario_path: str | Path, runs: int, log) -> MonteCarloStudy:
    """The bound (noise-free solve), then ``runs`` noise realisations, all on the cluster."""
    check_runs(runs)
    scenario = load_scenario(scenario_path)
    src = str(scenario_path)
    log("the bound: solving the noise-free session")
    bound = run_tasks(client, solve_noise_free, [("crb", (scenario, src))], log, log_failures=False)[0]
    if not bound.ok:
        raise InputError(scenario_path, "", "the noise-free session cannot be solved for the bound: "
                                            + bound.error.removeprefix(f"{scenario_path}: "))
    if bound.value.undetermined:
        raise InputError(scenario_path, "", f"the scenario cannot determine {len(bound.value.undetermined)} "
                                            f"direction(s): {'; '.join(bound.value.undetermined)} (castimate plan names them)")
    results = run_tasks(client, solve_simulated, [(f"run {k}", (scenario, k, False, src)) for k in range(runs)], log,
                        lambda s: f"chi2/dof {s.chi2_per_dof:.3g}")
    return score_study(src, bound.value, results)

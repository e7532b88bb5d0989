"""``castimate montecarlo``: simulate, solve and score many noise realisations of one scenario.

The scenario's ``seed`` fixes the truth (parameters, poses or motion); run k draws its noise from
the noise seed k (:func:`castimate.simulate.scenarios.simulate_scenario`), so every run estimates
the same truth and the bound is one: the σ's of a noise-free session's solution
(:func:`solve_noise_free`, also the engine of ``castimate plan``).

A scenario may carry a ``montecarlo`` section (taken out before it is simulated)::

    montecarlo:
      bound: measurements      # which bound the runs are scored against (BOUNDS)
      problem:                 # merged into every simulated problem.yaml: the estimator's settings
        model: {gyroscope: {time_offset: free}}

``tasks`` run on a Dask client, or one after the other in this process with client None
(:func:`castimate.scale.engine.run_tasks`): both are the same path.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from ..errors import InputError
from ..kinds import kind_of
from ..kinds.dynamic import MOTION_LEVEL_KEYS
from ..output import OUTPUTS
from ..simulate.scenarios import read_scenario, scenario_keys, simulate_scenario
from ..solver.ipopt import Solver
from ..solver.uncertainty import partial_bound
from ..spec import load_problem, motion_noise_setting
from ..validation import Check
from .engine import TaskResult, run_tasks
from .stats import Estimate, MonteCarloResult, estimates, score_runs, truth_values

MAX_RUNS = 10 ** 6

#: The bounds a study can be scored against (``montecarlo.bound``), each the σ's of one noise-free
#: session of the scenario's truth, solved as described.
BOUNDS = {
    "problem": "the Cramér-Rao bound of the problem as simulated: the σ's of the noise-free session's solution",
    "measurements": "the Cramér-Rao bound of the measurements alone: the noise-free session solved with the motion "
                    "free at every sample (motion.process_model: false), no assumption on the motion",
    "process_model": "the Fisher bound of the problem's process model: the noise-free session solved with the "
                     "process-noise levels held fixed (motion.process_noise: fixed) at the median of the levels the "
                     "runs estimated",
}
#: Bounds that change the motion model, for dynamic scenarios only.
DYNAMIC_BOUNDS = ("measurements", "process_model")
MONTECARLO_KEYS = ("bound", "problem")


@dataclass(frozen=True)
class StudySettings:
    """A scenario's ``montecarlo`` section: the bound's name and the problem keys every run's
    simulated problem.yaml is merged with (the estimator's settings)."""

    bound: str = "problem"
    problem: dict = field(default_factory=dict)


def study_settings(raw: dict, source: str | Path, bound: str | None = None) -> StudySettings:
    """The ``montecarlo`` section of a scenario mapping, checked (``bound``: overrides its bound)."""
    c = Check(Path(source))
    m = c.mapping(raw.get("montecarlo"), "montecarlo", MONTECARLO_KEYS)
    name = c.choice(m.get("bound", "problem") if bound is None else bound,
                    "montecarlo.bound" if bound is None else "--bound", tuple(BOUNDS))
    if name in DYNAMIC_BOUNDS and raw.get("kind") != "dynamic_array":
        c.fail("montecarlo.bound" if bound is None else "--bound",
               f"{name} changes the motion model: it is for kind dynamic_array, not {raw.get('kind')}")
    problem = c.mapping(m.get("problem"), "montecarlo.problem", None)
    for k in ("kind", "data"):
        if k in problem and (k == "kind" or "path" in (problem[k] or {})):
            c.fail(f"montecarlo.problem.{k}", "is the simulation's own: the runs solve the session the scenario "
                                              "simulates")
    return StudySettings(name, problem)


def merged(doc: dict, over: dict) -> dict:
    """``doc`` with ``over`` merged in: mappings key by key (recursively), anything else replaced."""
    out = dict(doc)
    for k, v in over.items():
        out[k] = merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def bound_problem(settings: StudySettings, levels: dict | None = None) -> dict:
    """The problem keys of the noise-free session of the settings' bound (``levels``: the process
    model's integration and levels, for the process_model bound)."""
    if settings.bound == "measurements":
        return {**settings.problem, "motion": {"process_model": False}}  # the process model's settings go too
    if settings.bound == "process_model":
        keys = MOTION_LEVEL_KEYS[levels["integration"]]
        return merged(settings.problem, {"motion": {"process_noise": "fixed", **{
            keys[k]: float(v) for k, v in levels["levels"].items()}}})
    return settings.problem


def load_scenario(path: str | Path, own: tuple[str, ...] = ("montecarlo",)) -> dict:
    """A scenario file's mapping, its kind and top-level keys checked (here, not from every worker's
    simulation after the cluster started; the values when first simulated); ``own``: the caller's
    sections beside the scenario's keys (montecarlo's ``montecarlo``, a plan's ``plan``)."""
    raw = read_scenario(path)
    Check(path).mapping({k: v for k, v in raw.items() if k not in own}, "", scenario_keys(raw["kind"]))
    return raw


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
    motion: dict | None = None  # results.json's motion_model: process_model, integration, levels (dynamic)
    correlation: tuple[list[str], np.ndarray] | None = None  # labels and correlation of the estimates (bounds)


def _simulate(scenario: dict, source: str, tmp: Path, noise_seed: int | None, noise_free: bool,
              problem: dict | None = None):
    path = tmp / (Path(source).name if source else "scenario.yaml")
    path.write_text(yaml.safe_dump(scenario, sort_keys=False))
    try:
        files = simulate_scenario(path, tmp / "sim", noise_seed=noise_seed, noise_free=noise_free)
    except InputError as e:  # name the user's file, not the worker's copy
        raise InputError(source or e.source, e.where, e.message) from None
    if problem:
        doc = merged(yaml.safe_load(files["problem"].read_text()), problem)
        files["problem"].write_text(yaml.safe_dump(doc, sort_keys=False))
    try:
        spec = load_problem(files["problem"])
    except InputError as e:
        if not problem:
            raise
        raise InputError(source or e.source, f"montecarlo.problem ({e.where or 'the merged problem'})",
                         e.message) from None
    return json.loads(files["truth"].read_text()), spec


def _motion(res: dict) -> dict | None:
    m = res.get("motion_model")
    return {k: m[k] for k in ("process_model", "integration", "levels") if k in m} if isinstance(m, dict) else None


def solve_simulated(scenario: dict, noise_seed: int | None = None, noise_free: bool = False, source: str = "",
                    problem: dict | None = None) -> Simulated:
    """On a worker: simulate the scenario (its truth, noise from ``noise_seed``), merge ``problem``
    into the simulated problem file and solve it through the kind's pipeline."""
    with tempfile.TemporaryDirectory(prefix="castimate-mc-") as tmp:
        truth, spec = _simulate(scenario, source, Path(tmp), noise_seed, noise_free, problem)
        kind = kind_of(spec)
        outcome = kind.calibrate(spec, kind.load(spec), quick=True)
        res = OUTPUTS[spec.kind].results(outcome)
    return Simulated(truth_values(truth), estimates(res), float(res["residuals"]["chi2_per_dof"]), motion=_motion(res))


def _correlation(outcome) -> tuple[list[str], np.ndarray] | None:
    solver, sol = getattr(outcome, "solver", None), getattr(outcome, "solution", None)
    if solver is None or sol is None or getattr(sol, "covariance", None) is None:
        return None
    C = np.asarray(sol.covariance, float)
    sd = np.sqrt(np.clip(np.diag(C), 0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = C / np.outer(sd, sd)
    labels = solver.problem.layout.x_labels
    return [labels[i] for i in solver.theta], rho


def solve_noise_free(scenario: dict, source: str = "", problem: dict | None = None) -> Simulated:
    """The scenario's session without noise, solved (``problem`` merged into its problem file):
    its estimates are the truth and their σ's the Cramér-Rao bound of the scenario's noise. Directions
    the data cannot determine are named (``undetermined``) and their parameters get an infinite
    bound, where the pipeline would refuse."""
    with tempfile.TemporaryDirectory(prefix="castimate-crb-") as tmp:
        truth, spec = _simulate(scenario, source, Path(tmp), None, True, problem)
        # the bound of the declared σ's: no motion-dependent noise fitted to the exact readings, and
        # the Fisher σ's (a sandwich of the exact readings' vanishing residuals would be zero)
        spec = replace(spec, noise=replace(spec.noise, motion_dependent=motion_noise_setting("none")),
                       uncertainty=replace(spec.uncertainty, residual_correlation="none"))
        kind = kind_of(spec)
        data = kind.load(spec)

        def checked():
            built = kind.build(kind.configure(spec, data), data)
            solver = Solver(built.lsq, spec.solver)
            return built, solver, solver.undetermined(built.lsq.layout.x0())

        # the dynamic pipeline checks at its own (gyro-aided) start, after the chip clocks' beats are
        # found: effects that need motion look undetermined at the layout's start of zero motion
        bad: tuple | list = ()
        if spec.kind != "dynamic_array":
            built, solver, bad = checked()
        if not bad:
            try:
                outcome = kind.calibrate(spec, data, quick=True)
            except InputError as e:
                if spec.kind != "dynamic_array" or "cannot determine" not in e.message:
                    raise
                built, solver, bad = checked()
                if not bad:
                    raise
            else:
                res = OUTPUTS[spec.kind].results(outcome)
                return Simulated(truth_values(truth), estimates(res), float(res["residuals"]["chi2_per_dof"]),
                                 motion=_motion(res), correlation=_correlation(outcome))
        # undetermined: solve anyway (the noise-free data are fitted exactly on a manifold of
        # solutions) and bound what is determined, on the subspace orthogonal to the null directions
        sol = solver.solve()
        labels = built.lsq.layout.x_labels
        if sol.success:
            std, free = partial_bound(solver, sol.x)
        else:
            std, free = np.full(len(solver.theta), np.nan), np.zeros(len(solver.theta), bool)
        lay = built.lsq.layout
        est = {labels[i]: Estimate(float("nan"), float("inf") if f else float(s), lay.group(labels[i].split("[")[0]).unit)
               for i, s, f in zip(solver.theta, std, free)}
        return Simulated(truth_values(truth), est, 0.0, tuple(bad))


@dataclass(frozen=True)
class MonteCarloStudy:
    scenario: str
    runs: int
    bound: Simulated  # the noise-free solve of the named bound: truth and CRB
    results: list[TaskResult]  # per run, a Simulated
    score: MonteCarloResult
    settings: StudySettings = StudySettings()
    bound_levels: dict | None = None  # the process_model bound's integration and levels

    def failures(self) -> dict[str, int]:
        """Failed runs by reason: not converged, invalid input (e.g. a refused session), other."""
        out: dict[str, int] = {}
        for r in self.results:
            if not r.ok:
                why = "not converged" if "did not converge" in r.error else \
                    "internal error" if r.error.startswith(("internal error", "the task failed")) else "refused"
                out[why] = out.get(why, 0) + 1
        return out

    def bound_document(self) -> dict:
        """montecarlo.json's ``bound``: its name, what it is, and the levels it was computed at."""
        out = {"name": self.settings.bound, "definition": BOUNDS[self.settings.bound]}
        if self.bound_levels is not None:
            out["process_noise_levels"] = self.bound_levels
        return out


def score_study(scenario: str, bound: Simulated, results: list[TaskResult], settings: StudySettings = StudySettings(),
                bound_levels: dict | None = None) -> MonteCarloStudy:
    ok = [r.value for r in results if r.ok]
    crb = {lab: e.std for lab, e in bound.estimates.items()}
    score = score_runs(bound.truth, crb, [s.estimates for s in ok], len(results) - len(ok))
    return MonteCarloStudy(scenario, len(results), bound, results, score, settings, bound_levels)


def median_levels(runs: list[Simulated], source) -> dict:
    """The process model's integration and the median of every level the runs estimated."""
    motions = [s.motion for s in runs if s.motion]
    if not motions or not all(m.get("process_model") for m in motions):
        raise InputError(source, "montecarlo.bound", "process_model needs the process model in the runs' problem "
                                                     "(motion.process_model: true)")
    integ = {m["integration"] for m in motions}
    if len(integ) != 1:
        raise InputError(source, "montecarlo.bound", f"the runs used several integrations {sorted(integ)}")
    return {"integration": integ.pop(), "levels": {k: float(np.median([m["levels"][k] for m in motions]))
                                                   for k in motions[0]["levels"]}, "runs": len(motions)}


def _bound(client, scenario: dict, src: str, problem: dict, log) -> Simulated:
    bound = run_tasks(client, solve_noise_free, [("crb", (scenario, src, problem))], log, log_failures=False)[0]
    if not bound.ok:
        raise InputError(src, "", "the noise-free session cannot be solved for the bound: "
                                  + bound.error.removeprefix(f"{src}: "))
    if bound.value.undetermined:
        raise InputError(src, "", f"the scenario cannot determine {len(bound.value.undetermined)} "
                                  f"direction(s): {'; '.join(bound.value.undetermined)} (castimate plan names them)")
    return bound.value


def run_montecarlo(client, scenario_path: str | Path, runs: int, log, bound: str | None = None) -> MonteCarloStudy:
    """The bound (a noise-free solve) and ``runs`` noise realisations, all on the cluster (client
    None: in this process). ``bound`` overrides the scenario's ``montecarlo.bound``; the
    process_model bound is solved after the runs, at their median estimated levels."""
    check_runs(runs)
    raw = load_scenario(scenario_path)
    src = str(scenario_path)
    settings = study_settings(raw, scenario_path, bound)
    scenario = {k: v for k, v in raw.items() if k != "montecarlo"}
    first = settings.bound != "process_model"
    if first:
        log(f"the bound ({settings.bound}): solving the noise-free session")
        crb = _bound(client, scenario, src, bound_problem(settings), log)
    results = run_tasks(client, solve_simulated, [(f"run {k}", (scenario, k, False, src, settings.problem))
                                                  for k in range(runs)], log,
                        lambda s: f"chi2/dof {s.chi2_per_dof:.3g}")
    levels = None
    if not first:
        levels = median_levels([r.value for r in results if r.ok], src)
        log(f"the bound ({settings.bound}): solving the noise-free session at the runs' median levels "
            + ", ".join(f"{k} {v:.4g}" for k, v in levels["levels"].items()))
        crb = _bound(client, scenario, src, bound_problem(settings, levels), log)
    return score_study(src, crb, results, settings, levels)

"""``castimate plan``: the Cramér-Rao bound of every parameter for a planned protocol, before any
data are taken, and how it falls with the protocol's duration.

A plan file is a scenario (``castimate simulate``'s format: the array, its pose set or motion
profile with rate and noise, a seed for the truth around nominal) with one more key::

    plan:
      durations: [5, 10, 20, 40]   # s

A duration is the time held in each pose (static: ``samples_per_pose`` = duration x ``rate``, pose
means) or the length of the motion (dynamic: ``samples`` = duration x ``rate``). Every case is the
noise-free session solved (:func:`castimate.scale.montecarlo.solve_noise_free`): the σ's of that
solution are the bound, from the Fisher information of castimate's own model
(:mod:`castimate.solver.uncertainty`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from ..validation import Check
from .engine import run_tasks
from .montecarlo import Simulated, load_scenario, solve_noise_free
from .stats import PlanCase

MAX_CASES = 50


@dataclass(frozen=True)
class Plan:
    path: Path
    scenario: dict  # without ``plan``
    durations: list[float]
    rate: float

    def case(self, duration: float) -> dict:
        """The scenario of one duration."""
        n = max(1, round(duration * self.rate))
        key = "samples" if self.scenario.get("kind") == "dynamic_array" else "samples_per_pose"
        return {**self.scenario, key: n}


def load_plan(path: str | Path) -> Plan:
    path = Path(path)
    raw = load_scenario(path, own=("plan",))
    c = Check(path)
    if "plan" not in raw:
        c.fail("(top level)", "missing required key 'plan' (plan: {durations: [seconds, ...]}); the rest is a "
                              "scenario as for castimate simulate")
    p = c.mapping(raw["plan"], "plan", ("durations",), required=("durations",))
    d = p["durations"]
    if not isinstance(d, list) or not d:
        c.fail("plan.durations", f"expected a non-empty list of durations in seconds, found {d!r}")
    if len(d) > MAX_CASES:
        c.fail("plan.durations", f"expected at most {MAX_CASES} durations, found {len(d)}")
    durations = [c.number(v, f"plan.durations[{i}]", positive=True, hi=1e6, unit="s") for i, v in enumerate(d)]
    if sorted(set(durations)) != durations:
        c.fail("plan.durations", f"expected increasing durations, found {durations}")
    scenario = {k: v for k, v in raw.items() if k != "plan"}
    if scenario.get("time_series"):
        c.fail("time_series", "a plan of a static protocol uses pose means (time_series: false): the bound needs "
                              "the declared noise σ")
    rate = c.number(scenario.get("rate", 100.0), "rate", positive=True, hi=1e5, unit="Hz")
    for dur in durations:
        if dur * rate < 1:
            c.fail("plan.durations", f"a duration of {dur:g} s at {rate:g} Hz holds no sample; expected at least "
                                     f"{1 / rate:g} s")
    return Plan(path, scenario, durations, rate)


def plan_case(duration: float, s: Simulated) -> PlanCase:
    return PlanCase(duration, {lab: e.std for lab, e in s.estimates.items()},
                    {lab: e.unit for lab, e in s.estimates.items()}, s.undetermined)


def run_plan(client, plan_path: str | Path, log) -> tuple[Plan, list[PlanCase]]:
    """The bound of every duration of the plan, one noise-free solve per duration on the cluster."""
    plan = load_plan(plan_path)
    results = run_tasks(client, solve_noise_free, [(f"{d:g} s", (plan.case(d), str(plan_path))) for d in plan.durations],
                        log, lambda s: f"{len(s.undetermined)} undetermined" if s.undetermined else "", log_failures=False)
    for r in results:
        if not r.ok:
            raise InputError(plan_path, "", f"the {r.name} case cannot be solved: "
                                            + r.error.removeprefix(f"{plan_path}: "))
    return plan, [plan_case(d, r.value) for d, r in zip(plan.durations, results)]

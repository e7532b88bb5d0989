"""Simulated sessions through ``castimate diagnose``: detection and false-alarm rates of its
effect candidates (benchmarks/diagnose_rates.py)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class DiagnoseTrial:
    """One simulated session through ``castimate diagnose``."""

    effect: str | None  # the undeclared effect in the data (None: none)
    seed: int
    added: tuple[str, ...]
    first: str  # the candidate ranked first by the score tests of round 1
    wall_s: float

    @property
    def detected(self) -> bool:
        """The effect was added, and added first."""
        return bool(self.added) and self.added[0] == self.effect

    @property
    def false_alarm(self) -> bool:
        """Something other than the simulated effect was added."""
        return any(a != self.effect for a in self.added)


def diagnose_trials(scenario: str | Path, effect: str | None, seeds, workdir: str | Path) -> list[DiagnoseTrial]:
    """Simulate the scenario with ``effect`` at its realistic magnitude (or none) for each seed and
    diagnose the simulated problem, which declares no effect."""
    import time

    import yaml

    from ..kinds.diagnose import diagnose
    from ..spec import load_problem
    from ..validation import load_yaml
    from .scenarios import simulate_scenario

    raw = load_yaml(scenario, "scenario file")
    raw.pop("effects", None)
    if effect:
        raw["effects"] = {effect: "realistic"}
    out = []
    for seed in seeds:
        d = Path(workdir) / f"{effect or 'none'}_{seed}"
        d.mkdir(parents=True, exist_ok=True)
        (d / "scenario.yaml").write_text(yaml.safe_dump({**raw, "seed": int(seed)}))
        files = simulate_scenario(d / "scenario.yaml", d)
        t0 = time.perf_counter()
        dg = diagnose(load_problem(files["problem"]), held_out=False)  # the decisions only
        out.append(DiagnoseTrial(effect, int(seed), tuple(dg.added), dg.rounds[0].tests[0].effect if dg.rounds else "",
                                 time.perf_counter() - t0))
    return out

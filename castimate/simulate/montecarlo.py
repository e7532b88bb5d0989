"""Monte Carlo checks of the estimator: are the reported σ's honest, and is the CRB reached?

One problem is built once; every run re-solves it with fresh noise passed as NLP parameters.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..problem.triads import ACCELEROMETER_GROUPS, GroupSetting, TriadConfig
from ..problem.static import DIRECTIONS, StaticConfig, build_static
from ..prepare.poses import pose_averages_from_means
from .static import pose_directions, random_static_truth, static_pose_means
from ..solver.ipopt import Solver


@dataclass
class MonteCarloResult:
    """Per calibration parameter (columns) and run (rows)."""

    labels: list[str]
    errors: np.ndarray  # estimate - truth, physical units
    z: np.ndarray  # error / reported σ of that run
    crb: np.ndarray  # Cramér-Rao bound σ at the truth
    failures: int  # runs that did not converge (excluded)

    @property
    def z_std(self) -> np.ndarray:
        return self.z.std(axis=0, ddof=1)

    @property
    def rmse_over_crb(self) -> np.ndarray:
        return np.sqrt((self.errors ** 2).mean(axis=0)) / self.crb


def monte_carlo_static(runs: int, n_triads: int = 14, n_poses: int = 20, sigma: float = 0.01,
                       samples_per_pose: int = 1000, seed: int = 0) -> MonteCarloResult:
    """Simulate a Nilsson-like array once (truth, poses) and solve ``runs`` noise realisations."""
    rng = np.random.default_rng(seed)
    names = [f"imu{i + 1}" for i in range(n_triads)]
    truth = random_static_truth(names, names[0], rng)
    U = pose_directions(n_poses, rng)
    free = GroupSetting(free=(True,) * 3)
    cfg = StaticConfig(tuple(TriadConfig(n, np.eye(3), {g: free for g in ACCELEROMETER_GROUPS}) for n in names),
                       names[0], truth.gravity)

    def poses(noise: bool):
        acc, _ = static_pose_means(truth, U, sigma if noise else 0.0, samples_per_pose, rng)
        return pose_averages_from_means(acc, samples_per_pose, sigma)

    exact = poses(False)
    prob = build_static(cfg, exact)
    solver = Solver(prob.lsq)
    lay = prob.lsq.layout
    true_values = dict(truth.values)
    true_values[DIRECTIONS] = U
    x_true = prob.x0(exact, true_values)
    calib = solver.theta
    crb = np.sqrt(np.diag(solver.covariance(x_true, data=prob.data_vector(exact))))
    scale = lay.x_scale[calib]
    errors, z, failures = [], [], 0
    for _ in range(runs):
        d = poses(True)
        sol = solver.solve(x0=prob.x0(d), data=prob.data_vector(d))
        if not sol.success:
            failures += 1
            continue
        e = (sol.x - x_true)[calib] * scale
        errors.append(e)
        z.append(e / np.sqrt(np.diag(sol.covariance)))
    labels = lay.x_labels
    return MonteCarloResult([labels[i] for i in calib], np.array(errors), np.array(z), crb, failures)


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
        dg = diagnose(load_problem(files["problem"]))
        out.append(DiagnoseTrial(effect, int(seed), tuple(dg.added), dg.rounds[0].tests[0].effect if dg.rounds else "",
                                 time.perf_counter() - t0))
    return out

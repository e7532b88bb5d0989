"""Whether the model fits: castimate.solver.verdict by hand, and the CLI saying so on a static session whose
noise σ is declared ten times too small (a converged solve whose model does not fit)."""

import json
import math

import pytest
import yaml

from castimate.cli import main
from castimate.solver.verdict import NO_FIT, fit_verdict


def test_fit_verdict_by_hand():
    """Each branch: not converged; no χ²/dof; χ²/dof above NO_FIT (residuals √(χ²/dof) × σ); nearly
    deterministic residuals (lag-1 autocorrelation above 0.7) at χ²/dof 1; above the 99 % band
    1 + 2.58 √(2/dof) (dof 200: 1.258); within it."""
    assert fit_verdict(False, "Maximum_Iterations_Exceeded", 1.0, 100) == (
        "bad", "The solver did not converge (Maximum_Iterations_Exceeded): the estimates are not valid.")
    assert fit_verdict(True, "Solve_Succeeded", None, 100)[0] == "warn"
    assert fit_verdict(True, "Solve_Succeeded", float("nan"), 100)[0] == "warn"
    level, sentence = fit_verdict(True, "Solve_Succeeded", 7402.06, 240000)
    assert level == "bad" and sentence.startswith("The model does not fit the data: χ²/dof = 7402, the residuals "
                                                  "are about 86 × the noise σ")
    assert NO_FIT == 4.0 and fit_verdict(True, "ok", 4.0, 10 ** 9)[0] == "warn"  # at the threshold: not "bad"
    level, sentence = fit_verdict(True, "ok", 1.0, 10 ** 6, {"accelerometer": {"a": 0.9, "b": 0.8}})
    assert level == "bad" and sentence.startswith("The model does not fit: the residuals' lag-1 autocorrelation is 0.85")
    band = 2.58 * math.sqrt(2 / 200)
    assert fit_verdict(True, "ok", 1 + 1.01 * band, 200)[0] == "warn"
    assert fit_verdict(True, "ok", 1 + 0.99 * band, 200) == ("ok", "The model fits the data: χ²/dof = 1.26, within "
                                                               "the noise model.")


def test_cli_says_when_the_model_does_not_fit(tmp_path, capsys):
    """A simulated static session (noise 0.02 m/s² per sample) solved as simulated fits; declared with a
    pose-mean σ ten times too small it still converges, at χ²/dof ≈ 100: exit 0, the summary warns that
    the model does not fit (residuals about 10 × the σ), and results.json's residuals.fit says "bad", as
    the outcome's ``fit`` does from Python."""
    sc = tmp_path / "scenario.yaml"
    sc.write_text("kind: static_array\nseed: 5\ntriads: 4\nposes: 20\nnoise: {accelerometer: 0.02}\n")
    assert main(["simulate", str(sc), "-o", str(tmp_path / "sim"), "-q"]) == 0
    capsys.readouterr()
    problem = tmp_path / "sim" / "problem.yaml"
    assert main(["solve", str(problem), "-o", str(tmp_path / "ok"), "-q"]) == 0
    assert "warning" not in capsys.readouterr().out
    fit = json.loads((tmp_path / "ok" / "results.json").read_text())["residuals"]["fit"]
    assert fit["level"] in ("ok", "warn") and "does not fit" not in fit["verdict"]

    doc = yaml.safe_load(problem.read_text())
    doc["noise"]["accelerometer"] /= 10
    (tmp_path / "sim" / "tight.yaml").write_text(yaml.safe_dump(doc))
    assert main(["solve", str(tmp_path / "sim" / "tight.yaml"), "-o", str(tmp_path / "tight"), "-q"]) == 0
    out = capsys.readouterr().out
    res = json.loads((tmp_path / "tight" / "results.json").read_text())["residuals"]
    chi2, dof = res["chi2_per_dof"], res["dof"]
    assert res["fit"]["level"] == "bad" and res["fit"]["verdict"].startswith("The model does not fit the data")
    # χ²/dof of the true σ is 1 ± 5 √(2/dof) (the fit as simulated), so 100 × that here
    assert chi2 == pytest.approx(100, rel=5 * math.sqrt(2 / dof) + 0.1)
    assert f"warning: The model does not fit the data: χ²/dof = {chi2:.4g}" in out
    # from Python: the outcome's fit is results.json's
    import castimate

    outcome = castimate.solve(castimate.load(tmp_path / "sim" / "tight.yaml"))
    assert outcome.fit == (res["fit"]["level"], res["fit"]["verdict"])

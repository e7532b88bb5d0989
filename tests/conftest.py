import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI does, before numpy loads (see castimate/cli.py)

from pathlib import Path  # noqa: E402

import matplotlib  # noqa: E402
import pytest  # noqa: E402

matplotlib.use("Agg")

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("CASTIMATE_SHARED_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real recordings beside the repository; CI has them, so their absence is a failure."""
    if not (SHARED_DATA / "README.md").is_file():
        pytest.fail(f"real data not found at {SHARED_DATA} (expected ../shared/data beside the repository)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def age_session(tmp_path_factory):
    """A small Carlsson-board session (4 IMUs x 300 samples, seed 5) with sub-millisecond chip sample
    ages, undeclared: (problem spec, directory with its data.csv and truth.json). Read-only."""
    import yaml

    from castimate.simulate.scenarios import simulate_scenario
    from castimate.spec import load_problem

    tmp = tmp_path_factory.mktemp("age")
    raw = yaml.safe_load((ROOT / "problems" / "sim_dynamic_effect_accelerometer_age.yaml").read_text())
    raw.update(seed=5, imus=4, samples=300)
    (tmp / "s.yaml").write_text(yaml.safe_dump(raw))
    return load_problem(simulate_scenario(tmp / "s.yaml", tmp)["problem"]), tmp


@pytest.fixture(scope="session")
def age_diagnosis(age_session):
    """``castimate diagnose``'s default (warm) path on :func:`age_session`, run once for the tests that
    read it (test_diagnose's chip sample age, test_diagnose_warm's warm path). Read-only: no test may
    mutate it."""
    from castimate.kinds.diagnose import diagnose

    return diagnose(age_session[0])

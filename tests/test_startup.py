"""The fixed costs of ``castimate solve`` around the solves: what it imports, and its memory
options (glibc's) held over the whole calibration."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from castimate.solver import ipopt

#: Modules a dynamic solve through the CLI does not need (plotting, the scheduler, scipy.stats's
#: distributions, the sparse LU of the full-NLP path): imported, they would cost start-up time.
NOT_IMPORTED = ("matplotlib", "dask", "distributed", "scipy.stats", "scipy.optimize", "scipy.sparse.linalg")


def test_cli_dynamic_solve_imports_only_what_it_needs(tmp_path):
    """A real ``castimate solve`` of a simulated dynamic session (motion eliminated, HAC σ's), run as
    the CLI runs, then the interpreter's modules: none of :data:`NOT_IMPORTED`, and the solve wrote
    its results."""
    scenario = {"kind": "dynamic_array", "seed": 3, "geometry": "carlsson", "imus": 4, "samples": 200, "rate": 62.5,
                "max_omega": 1000, "max_omega_dot": 20000, "euler_consistent": False,
                "motion": {"process_model": False}, "noise": {"pink": {"accelerometer": 0.04, "gyroscope": 0.06}}}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(scenario))
    from castimate.simulate.scenarios import simulate_scenario
    simulate_scenario(tmp_path / "s.yaml", tmp_path)
    script = ("import json, runpy, sys\n"
              f"sys.argv = ['castimate', 'solve', {str(tmp_path / 'problem.yaml')!r}, '-o', {str(tmp_path / 'out')!r}, '-q']\n"
              "try:\n    runpy.run_module('castimate', run_name='__main__')\nexcept SystemExit as e:\n    code = e.code\n"
              "from numpy._core.multiarray import _get_madvise_hugepage\n"
              f"print(json.dumps([code, sorted(m for m in {NOT_IMPORTED!r} if m in sys.modules), "
              "_get_madvise_hugepage()]))\n")
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", script], check=False, capture_output=True, text=True, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(root)}, timeout=300)
    code, imported, hugepage = json.loads(done.stdout.strip().splitlines()[-1])
    assert code == 0, done.stderr[-2000:]
    assert json.loads((tmp_path / "out" / "results.json").read_text())["kind"] == "dynamic_array"
    assert imported == []
    assert hugepage is False  # numpy's huge-page advice off (castimate.cli)


@pytest.mark.parametrize("env, advised", [({}, False), ({"NUMPY_MADVISE_HUGEPAGE": "1"}, True)])
def test_cli_turns_numpy_huge_page_advice_off_unless_the_user_set_it(env, advised):
    script = ("import castimate.cli\nimport numpy\nfrom numpy._core.multiarray import _get_madvise_hugepage\n"
              "print(_get_madvise_hugepage())\n")
    base = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, text=True,
                          env={**base, **env, "PYTHONPATH": str(root)}, timeout=60)
    assert done.stdout.split() == [str(advised)]


class FakeLibc:
    """Records glibc's mallopt and malloc_trim calls."""

    def __init__(self):
        self.calls = []

    def mallopt(self, param, value):
        self.calls.append(("mallopt", param, value))

    def malloc_trim(self, pad):
        self.calls.append(("malloc_trim", pad))


def test_nested_heap_allocation_leaves_the_defaults_to_the_outermost(monkeypatch):
    """``castimate solve`` holds heap_allocation over the calibration and a full-NLP solve opens its
    own inside: glibc's options are set once at the outer entry and restored (and the heap trimmed)
    only at the outer exit, also when the inner block raises."""
    libc = FakeLibc()
    monkeypatch.setattr(ipopt, "_glibc", lambda: libc)
    on = [("mallopt", ipopt._M_MMAP_MAX, 0), ("mallopt", ipopt._M_TRIM_THRESHOLD, 2**31 - 1)]
    off = [("mallopt", ipopt._M_MMAP_MAX, 65536), ("mallopt", ipopt._M_TRIM_THRESHOLD, 128 * 1024),
           ("malloc_trim", 0)]
    with ipopt.heap_allocation():
        assert libc.calls == on
        with pytest.raises(RuntimeError), ipopt.heap_allocation():
            raise RuntimeError("a failed solve")
        with ipopt.heap_allocation():
            pass
        assert libc.calls == on
    assert libc.calls == on + off
    with ipopt.heap_allocation():  # a later block sets them again
        pass
    assert libc.calls == on + off + on + off

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


def test_nested_solve_settings_leaves_the_defaults_to_the_outermost(monkeypatch):
    """``castimate solve`` holds solve_settings over the calibration and a full-NLP solve opens its
    own inside: glibc's options are set once at the outer entry and restored (and the heap trimmed)
    only at the outer exit, also when the inner block raises."""
    libc = FakeLibc()
    monkeypatch.setattr(ipopt, "_glibc", lambda: libc)
    on = [("mallopt", ipopt._M_MMAP_MAX, 0), ("mallopt", ipopt._M_TRIM_THRESHOLD, 2**31 - 1)]
    off = [("mallopt", ipopt._M_MMAP_MAX, 65536), ("mallopt", ipopt._M_TRIM_THRESHOLD, 128 * 1024),
           ("malloc_trim", 0)]
    with ipopt.solve_settings():
        assert libc.calls == on
        with pytest.raises(RuntimeError), ipopt.solve_settings():
            raise RuntimeError("a failed solve")
        with ipopt.solve_settings():
            pass
        assert libc.calls == on
    assert libc.calls == on + off
    with ipopt.solve_settings():  # a later block sets them again
        pass
    assert libc.calls == on + off + on + off


def test_solve_settings_turns_numpys_huge_page_advice_off_and_restores_it(monkeypatch):
    """NumPy's huge-page advice for large arrays is off inside the outermost block (also when a
    nested one raises) and back to what it was afterwards, whatever that was; left alone where the
    user chose it (NUMPY_MADVISE_HUGEPAGE set)."""
    state = {"on": True}

    def switch(enabled):
        previous, state["on"] = state["on"], bool(enabled)
        return previous

    monkeypatch.setattr(ipopt, "_numpy_hugepage", switch)
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    for before in (True, False):
        state["on"] = before
        with ipopt.solve_settings():
            assert not state["on"]
            with pytest.raises(RuntimeError), ipopt.solve_settings():
                raise RuntimeError("a failed solve")
            assert not state["on"]
        assert state["on"] == before
    monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")  # the user's choice stands
    state["on"] = True
    with ipopt.solve_settings():
        assert state["on"]


def test_numpys_huge_page_switch_is_found_and_left_as_it_was(monkeypatch):
    """The installed NumPy has the switch (else solve_settings would leave its advice on), and a
    real block leaves its setting as it found it."""
    switch = ipopt._numpy_hugepage
    assert switch is not None
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    before = switch(True)  # the switch returns the previous setting
    try:
        with ipopt.solve_settings():
            assert switch(False) is False  # off inside
        assert switch(True) is True
    finally:
        switch(before)


def test_solve_settings_run_every_openblas_on_one_thread_and_restore_them(monkeypatch):
    """Every OpenBLAS library loaded (CasADi's, NumPy's, SciPy's) runs on one thread inside the
    outermost block and on its earlier count afterwards; a count the user chose by the environment
    stays as it is. Found by name in this process: at least NumPy's and SciPy's are loaded here."""
    import scipy.linalg  # noqa: F401 - loads SciPy's OpenBLAS

    controls = ipopt._openblas_controls()
    assert len(controls) >= 2
    for v in ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS"):
        monkeypatch.delenv(v, raising=False)
    before = [get() for get, _ in controls]
    try:
        for _, put in controls:
            put(2)
        counts = [get() for get, _ in controls]  # 2, or what OpenBLAS allows on this machine
        with ipopt.solve_settings():
            assert [get() for get, _ in controls] == [1] * len(controls)
        assert [get() for get, _ in controls] == counts
        monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
        with ipopt.solve_settings():
            assert [get() for get, _ in controls] == counts
    finally:
        for (_, put), n in zip(controls, before):
            put(n)

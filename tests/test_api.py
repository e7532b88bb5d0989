"""The public Python surface: its docstring examples and the README's Python example run as written."""

import doctest
import os
import re
from pathlib import Path

import castimate
import castimate.api
from castimate.codegen import options as codegen_options

ROOT = Path(__file__).resolve().parents[1]


def run_doctests(module, monkeypatch):
    monkeypatch.chdir(ROOT)
    res = doctest.testmod(module, optionflags=doctest.ELLIPSIS, raise_on_error=False, verbose=False)
    assert res.attempted > 0 and res.failed == 0, f"{res.failed} of {res.attempted} examples failed (printed above)"


def test_api_docstring_examples_run(shared_data, monkeypatch):
    run_doctests(castimate.api, monkeypatch)


def test_codegen_options_examples_run(monkeypatch):
    run_doctests(codegen_options, monkeypatch)


def test_readme_python_example_runs(shared_data, monkeypatch, tmp_path):
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert blocks, "the README has no Python example"
    monkeypatch.chdir(ROOT)
    for code in blocks:
        code = code.replace('"out/', f'"{tmp_path}/')  # write into the test's directory, not the repository
        exec(compile(code, "README.md", "exec"), {})
    assert (tmp_path / "xsens" / "results.json").is_file()


def test_the_package_exposes_the_api_lazily():
    import castimate.solver.elimination as elimination  # the solver subpackage beside the API function
    from castimate.solver import Solver

    assert set(castimate.__all__) == set(castimate.api.__all__)
    assert castimate.solve is castimate.api.solve and Solver.__module__ == "castimate.solver.ipopt"
    assert elimination.__name__ == "castimate.solver.elimination"
    assert castimate.write is castimate.api.write
    assert set(castimate.__all__) <= set(dir(castimate))  # tab completion lists the lazy API (it listed none)
    assert "OPENBLAS_NUM_THREADS" in os.environ  # set by conftest, as the CLI does, before numpy loads


def test_write_takes_a_diagnosis_as_castimate_diagnose_writes_it(shared_data, monkeypatch, tmp_path):
    """castimate.write(castimate.diagnose(...)) writes the command's four files (it refused a Diagnosis),
    from a problem file and from the same problem as a dict; the refined problem file loads from where
    it was written and frees the added effects."""
    import json

    import yaml

    monkeypatch.chdir(ROOT)
    d = castimate.diagnose("problems/xsens_imutk.yaml")
    assert d.added  # the imu_tk session's drift and g-sensitivity: something to refine
    path = castimate.write(d, tmp_path / "file")
    assert path == tmp_path / "file" / "results.json"
    assert sorted(p.name for p in (tmp_path / "file").iterdir()) == \
        ["diagnose.json", "report.html", "results.json", "xsens_imutk_refined.yaml"]
    assert json.loads(path.read_text())["status"]["success"]
    doc = yaml.safe_load(open("problems/xsens_imutk.yaml"))
    from_dict = castimate.diagnose(castimate.load(doc, base_dir="problems"))
    assert from_dict.added == d.added
    castimate.write(from_dict, tmp_path / "dict")
    refined = castimate.load(tmp_path / "dict" / "problem_refined.yaml")
    assert refined.data.path.resolve() == (ROOT / "problems" / doc["data"]["path"]).resolve()
    assert refined.kind == "static_array"
    text = (tmp_path / "dict" / "problem_refined.yaml").read_text()
    assert "given as a dict" in text.splitlines()[0]
    model = yaml.safe_load(text)["model"]
    assert all(model[k.split(".")[0]][k.split(".")[1]] == "free" for k in d.added)

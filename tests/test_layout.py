"""The package's layering: every import points down, and no private name crosses a module.

The layers, lowest first (README, "Architecture"): a module may import from its own package and
from any lower layer, never from a higher one or a sibling on the same layer.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "castimate"

LAYERS = [
    ("errors", "jit", "version"),  # utilities without physics
    ("validation",),   # the one style of input checks
    ("models",),       # symbolic physics only
    ("problem",),      # factor graphs composed from the models, parameter groups, the effect registry
    ("solver",),       # IPOPT driver, numpy assembly, uncertainty, BCD
    ("io",),           # readers, units, recordings, atomic writes, results.json reading
    ("prepare",),      # static-segment detection, pose averages, sample masks
    ("spec",),         # problem file -> validated ProblemSpec
    ("kinds",),        # the pipelines: static, dynamic, diagnose
    ("calibration",),  # a calibration from results.json, applied to data
    ("simulate",),     # independent truth models, scenarios, Monte Carlo
    ("output",),       # results.json, diagnose.json, details.npz, summaries from outcomes
    ("scale",),        # Dask: batches, Monte Carlo studies, plans (the arithmetic in scale/stats.py)
    ("report",),       # HTML pages and figures
    ("codegen",),      # C emission
    ("api",),          # the public Python surface
    ("cli",),
    ("__main__",),
    ("__init__",),
]
RANK = {name: i for i, names in enumerate(LAYERS) for name in names}


def modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py"))


def unit(path: Path) -> str:
    """The top-level unit (package or module) a file belongs to."""
    rel = path.relative_to(PACKAGE)
    return rel.parts[0].removesuffix(".py")


def dotted(path: Path) -> list[str]:
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = ["castimate", *rel.parts]
    return parts[:-1] if parts[-1] == "__init__" else parts


def imported(path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, absolute module, names) of every castimate import in a file, nested ones included."""
    out = []
    here = dotted(path)
    package = here if path.name == "__init__.py" else here[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.startswith("castimate"):
                out.append((node.lineno, mod, [a.name for a in node.names]))
        elif isinstance(node, ast.Import):
            out += [(node.lineno, a.name, []) for a in node.names if a.name.startswith("castimate")]
    return out


def target_unit(mod: str, names: list[str]) -> list[str]:
    parts = mod.split(".")
    if len(parts) > 1:
        return [parts[1]]
    return names  # from castimate import x


def test_every_unit_has_a_layer():
    units = {unit(p) for p in modules()}
    assert units <= set(RANK), f"add these to LAYERS: {sorted(units - set(RANK))}"


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_down(path):
    me = unit(path)
    bad = []
    for line, mod, names in imported(path):
        for other in target_unit(mod, names):
            if other == me:
                continue
            if RANK[other] >= RANK[me]:
                bad.append(f"line {line}: {me} (layer {RANK[me]}) imports {mod} ({other}, layer {RANK[other]})")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_private_name_crosses_a_module(path):
    bad = [f"line {line}: from {mod} import {n}" for line, mod, names in imported(path)
           for n in names if n.startswith("_") and not n.startswith("__")]
    assert not bad, "\n".join(bad)


def module_aliases(path: Path) -> set[str]:
    """Names under which a file imports castimate modules (``from . import figures``)."""
    out = set()
    for _, mod, names in imported(path):
        base = PACKAGE.parent.joinpath(*mod.split("."))
        out |= {n for n in names if (base / f"{n}.py").exists() or (base / n / "__init__.py").exists()}
    return out


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_private_attribute_of_another_module(path):
    aliases = module_aliases(path)
    bad = [f"line {n.lineno}: {n.value.id}.{n.attr}" for n in ast.walk(ast.parse(path.read_text()))
           if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id in aliases
           and n.attr.startswith("_") and not n.attr.startswith("__")]
    assert not bad, "\n".join(bad)


def test_the_test_fails_on_an_upward_import(tmp_path, monkeypatch):
    """The check itself can fail: a models module that imports io is caught."""
    fake = PACKAGE / "models" / "rotation.py"
    text = fake.read_text() + "\nfrom ..io.recording import Recording\n"
    copy = tmp_path / "castimate" / "models" / "rotation.py"
    copy.parent.mkdir(parents=True)
    copy.write_text(text)
    monkeypatch.setattr(__import__(__name__), "PACKAGE", tmp_path / "castimate")
    with pytest.raises(AssertionError, match="imports castimate.io.recording"):
        test_imports_point_down(copy)

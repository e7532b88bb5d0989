"""``castimate batch``: one calibration per recording from a problem template, in parallel.

The template is a problem file whose ``data.path`` is replaced by each recording (every other key,
relative paths included, counts from the template's directory). Each calibration runs on a Dask
worker through the kind's pipeline and comes back as its results.json document and details.npz
bytes; a recording that fails is reported and the others go on.
"""

from __future__ import annotations

import copy
import glob
import hashlib
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from ..kinds import calibrate
from ..output import write_outputs
from ..output.tables import csv_text
from ..spec import ProblemSpec, parse_problem
from ..validation import Check, input_file, load_yaml
from .engine import TaskResult, run_tasks
from .stats import Estimate, ParameterSpread, batch_spread, estimates

#: |x - median| / σ above which a recording's parameter is flagged (the default of --outlier-threshold)
OUTLIER_THRESHOLD = 5.0
GLOB_CHARS = "*?["


def recordings_of(patterns: list[str]) -> list[Path]:
    """The recordings named by globs or paths, in the order given (globs sorted), each once."""
    if not patterns:
        raise InputError("RECORDINGS", "", "expected at least one recording (a path or a glob)")
    out: list[Path] = []
    for p in patterns:
        if any(ch in p for ch in GLOB_CHARS):
            found = sorted(glob.glob(p, recursive=True))
            if not found:
                raise InputError(p, "RECORDINGS", "the glob matches no file")
            files = [Path(f) for f in found if Path(f).is_file()]
            if not files:
                raise InputError(p, "RECORDINGS", f"the glob matches {len(found)} director(ies) and no file")
        else:
            input_file(p, "recording")
            files = [Path(p)]
        out += files
    unique = list(dict.fromkeys(f.resolve() for f in out))
    return unique


def recording_names(paths: list[Path]) -> list[str]:
    """Short unique names for result directories: the path below the recordings' common directory,
    without a file name they all share (``exp_1`` for .../exp_1/data.bin), else without its suffix."""
    if len(paths) == 1:
        return [paths[0].stem]
    common = Path(os.path.commonpath([str(p) for p in paths]))
    rel = [p.relative_to(common) for p in paths]
    same_file = len({r.name for r in rel}) == 1 and all(len(r.parts) > 1 for r in rel)
    parts = [r.parent.parts if same_file else (*r.parent.parts, r.stem if r.suffix else r.name) for r in rel]
    names = ["_".join(p) for p in parts]
    alt = ["_".join((*r.parent.parts, r.name)) for r in rel]
    if len(set(names)) < len(names) and len(set(alt)) == len(alt):  # suffixes alone told them apart (a.csv, a.npz)
        names = alt
    seen: dict[str, int] = {}
    for i, n in enumerate(names):  # joining with _ can still merge two paths (a_b/x.csv, a/b_x.csv)
        seen[n] = seen.get(n, 0) + 1
        if seen[n] > 1:  # numbered, else both would write DIR/<name>/results.json and one be lost
            k = seen[n]
            while f"{n}~{k}" in names or f"{n}~{k}" in seen:
                k += 1
            names[i] = f"{n}~{k}"
            seen[names[i]] = 1
    return names


@dataclass(frozen=True)
class Template:
    path: Path
    raw: dict

    def problem(self, recording: Path) -> ProblemSpec:
        """The template with data.path replaced by ``recording`` (absolute), validated."""
        raw = copy.deepcopy(self.raw)
        raw["data"]["path"] = str(Path(recording).resolve())
        text = json.dumps(raw, sort_keys=True, default=str)
        return parse_problem(raw, self.path.resolve(), hashlib.sha256(text.encode()).hexdigest())


def load_template(path: str | Path) -> Template:
    path = Path(path)
    raw = load_yaml(path, "problem template")
    c = Check(path)
    if not isinstance(raw, dict):
        c.fail("", f"expected a problem mapping, found {type(raw).__name__}")
    if not isinstance(raw.get("data"), dict):
        c.fail("data", "expected a mapping with the recording's path (replaced by each recording of the batch)")
    if any(k in raw["data"] for k in ("gyro_path", "sections")):
        c.fail("data", "a batch replaces data.path only: a template with a second data file (gyro_path, sections) "
                       "cannot be batched")
    return Template(path, raw)


def calibrate_recording(template: Template, recording: str) -> dict:
    """On a worker: calibrate one recording; its results.json document and the bytes of the files
    ``castimate solve`` writes."""
    spec = template.problem(Path(recording))
    outcome = calibrate(spec)
    with tempfile.TemporaryDirectory(prefix="castimate-batch-") as tmp:
        write_outputs(Path(tmp), outcome)
        files = {p.name: p.read_bytes() for p in Path(tmp).iterdir() if p.is_file()}
    return {"results": json.loads(files["results.json"]), "files": files}


def diagnose_recording(template: Template, recording: str) -> dict:
    """On a worker: ``castimate diagnose`` of one recording: the refined model's results.json
    document, the effects it added, and the bytes of results.json and diagnose.json."""
    from ..io.results import write_json
    from ..kinds.diagnose import diagnose
    from ..output.diagnosis import diagnosis_document, final_results

    d = diagnose(template.problem(Path(recording)))
    results = final_results(d)
    with tempfile.TemporaryDirectory(prefix="castimate-batch-") as tmp:
        write_json(Path(tmp) / "results.json", results)
        write_json(Path(tmp) / "diagnose.json", diagnosis_document(d))
        files = {p.name: p.read_bytes() for p in Path(tmp).iterdir()}
    return {"results": json.loads(files["results.json"]), "added": list(d.added), "files": files}


@dataclass(frozen=True)
class BatchSummary:
    """What a batch found, per recording and per parameter."""

    template: str
    names: list[str]
    recordings: list[str]
    results: list[TaskResult]
    spread: list[ParameterSpread]
    threshold: float

    def outliers_of(self, name: str) -> dict[str, float]:
        return {s.label: s.z[name] for s in self.spread if name in s.outliers(self.threshold)}

    def rows(self) -> list[dict]:
        """One row per recording: status, fit and outliers."""
        out = []
        for name, rec, r in zip(self.names, self.recordings, self.results):
            res = r.value["results"] if r.ok else {}
            fit = res.get("residuals", {})
            st = res.get("status", {})
            out.append({"name": name, "recording": rec, "status": "ok" if r.ok else "failed",
                        "message": st.get("message", "") if r.ok else r.error,
                        "chi2_per_dof": fit.get("chi2_per_dof"), "dof": fit.get("dof"),
                        "iterations": st.get("iterations"), "wall_s": r.wall_s,
                        "outliers": len(self.outliers_of(name)) if r.ok else None,
                        "added_effects": " ".join(r.value["added"]) if r.ok and "added" in r.value else None})
        return out

    def document(self) -> dict:
        return {"format": "castimate.batch/1", "template": self.template, "outlier_threshold": self.threshold,
                "recordings": [dict(row, outlier_parameters=self.outliers_of(row["name"])) for row in self.rows()],
                "parameters": [{"label": s.label, "unit": s.unit, "median": s.median, "spread": s.spread,
                                "median_sigma": s.sigma, "spread_over_sigma": s.spread_over_sigma,
                                "median_sigma_scaled": s.sigma_scaled, "z": s.z,
                                "outliers": s.outliers(self.threshold)} for s in self.spread]}

    def csv(self) -> str:
        return csv_text(self.rows())


def summarise(template: str, names: list[str], recordings: list[str], results: list[TaskResult],
              threshold: float = OUTLIER_THRESHOLD) -> BatchSummary:
    ok = {n: r.value["results"] for n, r in zip(names, results) if r.ok}
    params: dict[str, dict[str, Estimate]] = {n: estimates(res) for n, res in ok.items()}
    chi2 = {n: float(res["residuals"]["chi2_per_dof"]) for n, res in ok.items()}
    return BatchSummary(template, names, recordings, results, batch_spread(params, chi2) if params else [], threshold)


def check_threshold(threshold: float) -> float:
    """``--outlier-threshold``: a positive, finite number of σ's (infinity would flag nothing)."""
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not 0 < threshold < float("inf"):
        raise InputError("--outlier-threshold", "", f"expected a positive finite number of σ's, found {threshold!r}")
    return threshold


def run_batch(client, template_path: str | Path, patterns: list[str], log, threshold: float = OUTLIER_THRESHOLD,
              diagnose: bool = False) -> BatchSummary:
    """Check the template and recordings here, then calibrate every recording on the cluster
    (``diagnose``: through ``castimate diagnose``, adding the effects each recording demands)."""
    check_threshold(threshold)
    template = load_template(template_path)
    recordings = recordings_of(patterns)
    template.problem(recordings[0])  # a bad template fails here, once, not on every worker
    names = recording_names(recordings)
    log(f"batch: {len(recordings)} recordings of {template_path}")

    def describe(v: dict) -> str:
        added = f", added: {' '.join(v['added']) or 'nothing'}" if "added" in v else ""
        return f"chi2/dof {v['results']['residuals']['chi2_per_dof']:.3g}{added}"

    task = diagnose_recording if diagnose else calibrate_recording
    results = run_tasks(client, task, [(n, (template, str(r))) for n, r in zip(names, recordings)], log, describe)
    return summarise(str(template_path), names, [str(r) for r in recordings], results, threshold)

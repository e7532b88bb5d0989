"""Adversarial inputs through the command line: no traceback, no silent wrong answer, no touched input.

Every case runs ``castimate.cli.main([...])`` in a forked child (memory and time limited, so that a
case which would read a device forever or allocate without bound ends as a failure, not a hang)
and asserts:

- the exit code (0 success, 2 invalid input, 3 not converged);
- for a refusal, ONE line ``castimate <verb>: error: ...`` naming the right file, key or column;
- every input file byte-identical afterwards, and no partial output (a refused run leaves the case
  directory exactly as it was, hidden temporary files included).

The data are tiny sessions simulated once per run (``castimate simulate``) and written in every
reader's format (csv, npz, the MIMU packet stream, imu_tk tables). :func:`outcome` classifies a run
as clean / vague / traceback / wrong success / touched input; ``python tests/test_adversarial.py``
prints the table per issue class.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import resource
import shutil
import signal
import sys
import traceback
from collections import Counter
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import yaml

from castimate.cli import main
from castimate.io.readers import read_csv, write_npz
from castimate.io.recording import Recording

# ============================================================================ running a case


def _vm_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    return 0


def run_cli(argv: list[str], timeout: int = 60, extra_memory: int = 3 << 30) -> dict:
    """``main(argv)`` in a forked child: {'rc', 'stdout', 'stderr', 'exception', 'killed'}."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child
        os.close(r)
        out, err = io.StringIO(), io.StringIO()
        res = {"rc": None, "exception": None, "killed": None}
        try:
            lim = _vm_bytes() + extra_memory
            resource.setrlimit(resource.RLIMIT_AS, (lim, lim))
            signal.alarm(timeout)
            with redirect_stdout(out), redirect_stderr(err):
                try:
                    res["rc"] = main(argv)
                except SystemExit as e:
                    res["rc"] = e.code if isinstance(e.code, int) else 1
                except BaseException:  # noqa: BLE001 - anything escaping main is the finding
                    res["exception"] = traceback.format_exc()
        except BaseException:  # noqa: BLE001
            res["exception"] = traceback.format_exc()
        res["stdout"], res["stderr"] = out.getvalue(), err.getvalue()
        data = json.dumps(res).encode()
        with os.fdopen(w, "wb") as fh:
            fh.write(data)
        os._exit(0)
    os.close(w)
    with os.fdopen(r, "rb") as fh:
        data = fh.read()
    _, status = os.waitpid(pid, 0)
    if not data:
        sig = os.WTERMSIG(status) if os.WIFSIGNALED(status) else None
        return {"rc": None, "stdout": "", "stderr": "", "exception": None,
                "killed": f"signal {sig}" + (" (time limit)" if sig == signal.SIGALRM else "")}
    return json.loads(data)


def snapshot(*roots: Path) -> dict[str, str]:
    """Path -> sha256 of every file (hidden ones too) under the roots; directories as 'dir'."""
    out = {}
    for root in roots:
        if not root.exists():
            continue
        items = [root] if root.is_file() else [root, *sorted(root.rglob("*"))]
        for p in items:
            if p.is_symlink():
                out[str(p)] = "link:" + os.readlink(p)
            elif p.is_file():
                out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
            elif p.is_dir():
                out[str(p)] = "dir"
            else:
                out[str(p)] = "special"
    return out


@dataclass
class Spec:
    """What a case runs and expects."""

    argv: list[str]
    rc: int = 2
    names: tuple[str, ...] = ()  # fragments the error line must contain (file, key, column, ...)
    output: Path | None = None  # where a successful run writes (new files allowed only under it)
    check: Callable[[dict], str | None] | None = None  # extra check of a success: a failure reason or None
    timeout: int = 60  # s of wall time for the child


@dataclass
class Case:
    id: str
    klass: str  # the issue's class: traceback, silent, touched, vague, cli
    build: Callable[[Path, Path], Spec]  # (base dir, case dir) -> Spec
    marks: tuple = field(default_factory=tuple)


OUTCOMES = ("clean", "vague", "traceback", "wrong success", "touched input", "partial output")


def outcome(spec: Spec, res: dict, before: dict, after: dict, tmp: Path | None = None) -> tuple[str, str]:
    """Classify a run; return (outcome, explanation). Fragments are matched with ``tmp`` (the case's
    directory, whose name holds the case id) replaced by ``<tmp>``."""
    if res["killed"]:
        return "traceback", f"child killed: {res['killed']}"
    if res["exception"]:
        return "traceback", res["exception"].strip().splitlines()[-1]
    if "Traceback" in res["stderr"]:
        return "traceback", res["stderr"][-300:]
    changed = [p for p in before if after.get(p) != before[p]]
    if changed:
        return "touched input", f"changed or removed: {changed}"
    new = [p for p in after if p not in before]
    if res["rc"] != 0 and new:
        return "partial output", f"partial output left: {new}"
    if res["rc"] == 0 and spec.output is not None:
        stray = [p for p in new if not (p == str(spec.output) or p.startswith(str(spec.output) + os.sep))]
        if stray:
            return "touched input", f"wrote outside the output: {stray}"
    err_lines = [ln for ln in res["stderr"].splitlines() if ln.strip()]
    if spec.rc != 0:
        if res["rc"] == 0:
            return "wrong success", "exit 0; expected a refusal"
        last = err_lines[-1] if err_lines else ""
        if res["rc"] != spec.rc:
            return "vague", f"exit {res['rc']} (expected {spec.rc}): {last}"
        if not (last.startswith("castimate ") and ": error: " in last) and not last.startswith("usage:") \
                and "error:" not in last:
            return "vague", f"no one-line error: {last!r}"
        blank = (lambda x: x.replace(str(tmp), "<tmp>")) if tmp else (lambda x: x)
        missing = [n for n in spec.names if blank(n).lower() not in blank(last).lower()]
        if missing:
            return "vague", f"does not name {missing}: {last}"
        return "clean", last
    if res["rc"] != 0:
        return "vague" if res["rc"] in (2, 3) else "traceback", \
            f"exit {res['rc']}, expected success: {err_lines[-1] if err_lines else ''}"
    if spec.check is not None:
        why = spec.check(res)
        if why:
            return "wrong success", why
    return "clean", "ok"


# ============================================================================ base data

G = 9.80665
ACC_COUNTS = 2048 / G  # MIMU default: raw * 9.80665 / 2048 m/s^2
GYRO_COUNTS = 16.4 * 180 / np.pi  # raw / 16.4 deg/s
IMUTK_ACC = {"unit": "counts", "offset": 32768, "scale": 0.0024154589}
IMUTK_GYRO = {"unit": "counts", "offset": 32768, "scale": 0.00020964361}


def write_yaml(path: Path, doc) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def mimu_stream(ticks: np.ndarray, counter: np.ndarray, values: np.ndarray, ack: bytes = b"\x00\x01\x02\x03") -> bytes:
    """An OpenShoe/MIMU packet stream: values (M, n_imus, 6) int16, ticks uint32, counter uint16."""
    n = values.shape[1]
    psize = 4 + 12 * n
    out = bytearray(ack)
    for k in range(len(ticks)):
        body = bytes([0xAA]) + int(counter[k] % 65536).to_bytes(2, "big") + bytes([psize]) \
            + int(ticks[k] % (1 << 32)).to_bytes(4, "big") + values[k].astype(">i2").tobytes()
        out += body + (sum(body) & 0xFFFF).to_bytes(2, "big")
    return bytes(out)


def mimu_values(rec: Recording, names: list[str]) -> np.ndarray:
    v = np.stack([np.hstack([rec.acc[n] * ACC_COUNTS, rec.gyro[n] * GYRO_COUNTS]) for n in names], axis=1)
    return np.round(v).astype(np.int16)


def imutk_table(t: np.ndarray, xyz: np.ndarray, scale: float, offset: float = 32768) -> str:
    counts = xyz / scale + offset
    return "\n".join(f"{a:.7e}   {b:.7e}   {c:.7e}   {d:.7e}" for a, b, c, d in np.column_stack([t, counts])) + "\n"


def static_problem(data: str, fmt: str, names: list[str], **extra) -> dict:
    doc = {"kind": "static_array", "data": {"path": data, "format": fmt, "segments": "auto"},
           "array": {"reference": names[0], "triads": [{"name": n} for n in names]},
           "model": {"gravity": 9.81}, "noise": {"accelerometer": "auto"}}
    for k, v in extra.items():
        doc[k] = v
    return doc


def cli(*argv) -> None:
    res = run_cli([str(a) for a in argv])
    assert res["rc"] == 0, res


@pytest.fixture(scope="session")
def base(tmp_path_factory) -> Path:
    """Tiny simulated sessions in every format, solved once; read-only for the cases."""
    return build_base(tmp_path_factory.mktemp("base"))


def build_base(b: Path) -> Path:
    # static time series: 3 triads with gyroscopes, 12 poses of 4 s at 50 Hz (~3000 rows)
    (b / "static").mkdir()
    (b / "static.yaml").write_text("kind: static_array\ntriads: 3\nposes: 12\nseed: 1\ntime_series: true\n"
                                   "rate: 50\npose_duration: 4\ntransition: 1\ngyroscope: true\n")
    cli("simulate", b / "static.yaml", "-o", b / "static")
    # one row per pose: the fastest static solve
    (b / "rows.yaml").write_text("kind: static_array\ntriads: 3\nposes: 20\nseed: 2\n")
    cli("simulate", b / "rows.yaml", "-o", b / "rows")
    cli("solve", b / "rows" / "problem.yaml", "-o", b / "rows_solved", "-q")
    cli("solve", b / "static" / "problem.yaml", "-o", b / "static_solved", "-q")
    # dynamic: 4 IMUs of the Carlsson board with gyroscopes, 200 samples
    (b / "dyn.yaml").write_text("kind: dynamic_array\ngeometry: carlsson\nimus: 4\nsamples: 200\nseed: 3\n")
    cli("simulate", b / "dyn.yaml", "-o", b / "dyn")
    cli("solve", b / "dyn" / "problem.yaml", "-o", b / "dyn_solved", "-q")

    rec = read_csv(b / "static" / "data.csv")
    names = rec.triads
    # npz
    write_npz(b / "static.npz", rec)
    write_yaml(b / "npz.yaml", static_problem("static.npz", "npz", names))
    # MIMU packet stream: 2 IMUs; the timestamp starts 10 samples before a 2^32 wrap (a genuine wrap)
    n = len(rec.t)
    dt_ticks = round(64e6 / 50)
    ticks = (1 << 32) - 10 * dt_ticks + dt_ticks * np.arange(n, dtype=np.int64)
    counter = 65530 + np.arange(n)
    (b / "mimu.bin").write_bytes(mimu_stream(ticks, counter, mimu_values(rec, names[:2])))
    write_yaml(b / "mimu.yaml", static_problem("mimu.bin", "mimu", ["imu1", "imu2"]))
    cli("solve", b / "mimu.yaml", "-o", b / "mimu_solved", "-q")
    np.save(b / "mimu_parts.npy", np.column_stack([ticks, counter]))
    # imu_tk tables: imu1 in counts
    (b / "acc.mat").write_text(imutk_table(rec.t, rec.acc["imu1"], IMUTK_ACC["scale"]))
    (b / "gyro.mat").write_text(imutk_table(rec.t, rec.gyro["imu1"], IMUTK_GYRO["scale"]))
    doc = static_problem("acc.mat", "imutk", ["imu"])
    doc["data"].update(gyro_path="gyro.mat", units={"accelerometer": IMUTK_ACC, "gyroscope": IMUTK_GYRO})
    write_yaml(b / "imutk.yaml", doc)
    cli("solve", b / "imutk.yaml", "-o", b / "imutk_solved", "-q")
    # Ferraris: one IMU, six faces and three turns in imucal's files (castimate.simulate.ferraris)
    from castimate.simulate.ferraris import ferraris_session, write_imucal
    from castimate.simulate.static import StaticTruthScale, random_static_truth

    rng = np.random.default_rng(4)
    truth = random_static_truth(["imu"], "imu", rng, gyroscope=True,
                                scale=StaticTruthScale(gyro_gain=0.02, gyro_misalignment=0.01))
    write_imucal(b / "ferraris", *ferraris_session(truth, rng, hold=3.0, turn=2.0))
    write_yaml(b / "ferraris" / "problem.yaml", ferraris_doc())
    cli("solve", b / "ferraris" / "problem.yaml", "-o", b / "ferraris_solved", "-q")
    for p in b.rglob("*"):
        if p.is_file():
            p.chmod(0o444)
    return b


def copy(src: Path, dst_dir: Path, name: str | None = None) -> Path:
    dst = dst_dir / (name or src.name)
    shutil.copyfile(src, dst)
    return dst


def load_rec(base: Path) -> Recording:
    return read_csv(base / "static" / "data.csv")


def with_data(base: Path, tmp: Path, rec: Recording, fmt: str = "csv", problem: dict | None = None,
              name: str = "data") -> Path:
    """Write rec (csv or npz) and a static problem for it into tmp; return the problem path."""
    from castimate.io.readers import write_csv

    path = tmp / f"{name}.{fmt}"
    (write_csv if fmt == "csv" else write_npz)(path, rec)
    doc = problem or static_problem(path.name, fmt, rec.triads)
    doc["data"]["path"] = path.name
    return write_yaml(tmp / "problem.yaml", doc)


def edited(rec: Recording, **kw) -> Recording:
    d = dict(t=rec.t, acc=dict(rec.acc), gyro=dict(rec.gyro), temp=dict(rec.temp), source=rec.source)
    d.update(kw)
    return Recording(**d)


def problem_doc(base: Path, which: str = "static") -> dict:
    doc = yaml.safe_load((base / which / "problem.yaml").read_text())
    return doc


def problem_in(base: Path, tmp: Path, which: str, edit: Callable[[dict], None] | None = None,
               text: str | None = None) -> Path:
    """A copy of base/<which>/problem.yaml in tmp with data.path pointing at base's data."""
    doc = problem_doc(base, which)
    doc["data"]["path"] = str(base / which / "data.csv")
    if edit:
        edit(doc)
    p = tmp / "problem.yaml"
    if text is not None:
        p.write_text(text)
    else:
        write_yaml(p, doc)
    return p


def results_doc(base: Path, which: str = "rows_solved") -> dict:
    return json.loads((base / which / "results.json").read_text())


def solved_copy(base: Path, tmp: Path, which: str = "rows_solved", results=None, details=None) -> Path:
    """A copy of a solved directory, with results.json / details.npz edited."""
    d = tmp / "solved"
    d.mkdir()
    if results is not None:
        doc = results_doc(base, which)
        results(doc)
        (d / "results.json").write_text(json.dumps(doc))
    else:
        copy(base / which / "results.json", d)
    with np.load(base / which / "details.npz") as z:
        arrays = {k: z[k] for k in z.files}
    if details is not None:
        details(arrays)
    np.savez(d / "details.npz", **arrays)
    return d


# ============================================================================ the cases

CASES: list[Case] = []


def case(klass: str, *marks):
    def deco(fn):
        CASES.append(Case(fn.__name__, klass, fn, marks))
        return fn
    return deco


# ---------------------------------------------------------------- tracebacks


@case("traceback")
def no_static_pose_one_long_rest(base, tmp):
    """The array never moves: one rest, noise only (no pose directions to fit)."""
    rec = load_rec(base)
    rng = np.random.default_rng(5)
    rest = {n: a[:1] + 0.02 * rng.standard_normal((len(rec.t), 3)) for n, a in rec.acc.items()}
    grest = {n: a[:1] + 0.002 * rng.standard_normal((len(rec.t), 3)) for n, a in rec.gyro.items()}
    p = with_data(base, tmp, edited(rec, acc=rest, gyro=grest))
    return Spec(["solve", str(p), "-o", str(tmp / "out")], 2, ("problem.yaml", "pose"))


@case("traceback")
def no_static_pose_continuous_motion(base, tmp):
    p = tmp / "problem.yaml"
    doc = static_problem(str(base / "dyn" / "data.csv"), "csv", ["imu1", "imu11", "imu22", "imu32"])
    write_yaml(p, doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out")], 2, ("pose",))


@case("traceback")
def dynamic_motion_undetermined_no_gyro_no_process_model(base, tmp):
    def edit(d):
        for t in d["array"]["triads"]:
            t["gyroscope"] = False
        d["noise"].pop("gyroscope", None)  # unused with every gyroscope off: refused on its own
        d["motion"] = {"process_model": False}
    p = problem_in(base, tmp, "dyn", edit)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "motion.process_model"))


def _out_file(verb_argv):
    def build(base, tmp):
        (tmp / "taken").write_text("not a directory\n")
        argv, names = verb_argv(base, tmp, tmp / "taken")
        return Spec(argv, 2, names)
    return build


def _solve_argv(base, tmp, out):
    return ["solve", str(base / "rows" / "problem.yaml"), "-o", str(out), "-q"], (str(out),)


def _simulate_argv(base, tmp, out):
    return ["simulate", str(base / "rows.yaml"), "-o", str(out)], (str(out),)


def _diagnose_argv(base, tmp, out):
    return ["diagnose", str(base / "rows" / "problem.yaml"), "-o", str(out), "-q"], (str(out),)


def _codegen_argv(base, tmp, out):
    return ["codegen", str(base / "rows_solved" / "results.json"), "-o", str(out)], (str(out),)


def _apply_argv(base, tmp, out):
    return ["apply", str(base / "static_solved" / "results.json"), str(base / "static" / "data.csv"),
            "-o", str(out)], (str(out),)


OUTPUT_VERBS = {"solve": _solve_argv, "simulate": _simulate_argv, "diagnose": _diagnose_argv,
                "codegen": _codegen_argv}

for _verb, _argv in OUTPUT_VERBS.items():
    def _file_as_dir(base, tmp, _argv=_argv):
        (tmp / "taken").write_text("a file\n")
        argv, names = _argv(base, tmp, tmp / "taken")
        return Spec(argv, 2, names + ("directory",))

    def _under_file(base, tmp, _argv=_argv):
        (tmp / "taken").write_text("a file\n")
        out = tmp / "taken" / "sub"
        argv, names = _argv(base, tmp, out)
        return Spec(argv, 2, (str(tmp / "taken"),))

    CASES.append(Case(f"{_verb}_output_is_a_file", "traceback", _file_as_dir))
    CASES.append(Case(f"{_verb}_output_not_creatable", "traceback", _under_file))


@case("traceback")
def solve_output_file_slot_is_a_directory(base, tmp):
    out = tmp / "out"
    (out / "results.json").mkdir(parents=True)
    return Spec(["solve", str(base / "rows" / "problem.yaml"), "-o", str(out), "-q"], 2,
                (str(out / "results.json"), "directory"))


@case("traceback")
def report_output_slot_is_a_directory(base, tmp):
    d = solved_copy(base, tmp)
    (d / "report.html").mkdir()
    return Spec(["report", str(d)], 2, (str(d / "report.html"), "directory"))


@case("traceback")
def apply_output_is_a_directory(base, tmp):
    (tmp / "out.csv").mkdir()
    argv, _ = _apply_argv(base, tmp, tmp / "out.csv")
    return Spec(argv, 2, (str(tmp / "out.csv"), "directory"))


@case("traceback")
def apply_output_not_creatable(base, tmp):
    (tmp / "taken").write_text("a file\n")
    argv, _ = _apply_argv(base, tmp, tmp / "taken" / "out.csv")
    return Spec(argv, 2, (str(tmp / "taken"),))


@case("traceback")
def problem_not_utf8(base, tmp):
    p = tmp / "problem.yaml"
    p.write_bytes((base / "rows" / "problem.yaml").read_bytes().replace(b"# Simulated", b"# Simul\xe9 \xff"))
    (tmp / "data.csv").symlink_to(base / "rows" / "data.csv")
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "UTF-8"))


@case("traceback")
def scenario_not_utf8(base, tmp):
    p = tmp / "scenario.yaml"
    p.write_bytes(b"# caf\xe9\nkind: static_array\ntriads: 3\n")
    return Spec(["simulate", str(p), "-o", str(tmp / "out")], 2, ("scenario.yaml", "UTF-8"))


@case("traceback")
def problem_deeply_nested(base, tmp):
    p = tmp / "problem.yaml"
    p.write_text("kind: static_array\ndata: " + "[" * 20000 + "]" * 20000 + "\n")
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "nest"))


@case("traceback")
def scenario_deeply_nested(base, tmp):
    p = tmp / "scenario.yaml"
    p.write_text("kind: static_array\ntruth: " + "{a: " * 5000 + "1" + "}" * 5000 + "\n")
    return Spec(["simulate", str(p), "-o", str(tmp / "out")], 2, ("scenario.yaml", "nest"))


@case("traceback")
def problem_huge_integer(base, tmp):
    p = problem_in(base, tmp, "rows", lambda d: d.setdefault("solver", {}).update(max_iter=10 ** 400))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("solver.max_iter", "digits"))


@case("traceback")
def problem_huge_integer_gravity(base, tmp):
    p = problem_in(base, tmp, "rows", lambda d: d["model"].update(gravity=10 ** 400))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("model.gravity", "digits"))


@case("traceback")
def scenario_huge_integer_seed(base, tmp):
    p = tmp / "scenario.yaml"
    p.write_text(f"kind: static_array\ntriads: 3\nseed: {10 ** 400}\n")
    return Spec(["simulate", str(p), "-o", str(tmp / "out")], 2, ("seed", "digits"))


@case("traceback")
def problem_huge_file(base, tmp):
    p = problem_in(base, tmp, "rows")
    with open(p, "a") as fh:
        fh.write("#" + "x" * (2 << 20) + "\n")
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "MB"))


@case("traceback")
def data_path_is_a_device(base, tmp):
    p = problem_in(base, tmp, "static", lambda d: d["data"].update(path="/dev/zero"))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.path", "/dev/zero", "regular file"))


@case("traceback")
def data_path_is_a_fifo(base, tmp):
    os.mkfifo(tmp / "fifo.csv")
    p = problem_in(base, tmp, "static", lambda d: d["data"].update(path="fifo.csv"))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.path", "fifo.csv", "regular file"))


@case("traceback")
def problem_is_a_device(base, tmp):
    return Spec(["solve", "/dev/zero", "-o", str(tmp / "out"), "-q"], 2, ("/dev/zero", "regular file"))


@case("traceback")
def scenario_is_a_device(base, tmp):
    return Spec(["simulate", "/dev/zero", "-o", str(tmp / "out")], 2, ("/dev/zero", "regular file"))


@case("traceback")
def apply_data_is_a_device(base, tmp):
    return Spec(["apply", str(base / "static_solved" / "results.json"), "/dev/zero", "--format", "csv",
                 "-o", str(tmp / "out.csv")], 2, ("/dev/zero", "regular file"))


@case("traceback")
def apply_results_is_a_device(base, tmp):
    return Spec(["apply", "/dev/zero", str(base / "static" / "data.csv"), "-o", str(tmp / "out.csv")], 2,
                ("/dev/zero", "regular file"))


@case("traceback")
def codegen_source_is_a_device(base, tmp):
    return Spec(["codegen", "/dev/zero", "-o", str(tmp / "out")], 2, ("/dev/zero", "regular file"))


def _results_edit(path_keys, value):
    def f(doc):
        d = doc
        for k in path_keys[:-1]:
            d = d[k]
        if value is KeyError:
            del d[path_keys[-1]]
        else:
            d[path_keys[-1]] = value
    return f


RESULTS_DEFECTS = {
    # name: (edit, key named, apply-able)
    "parameter_value_string": (_results_edit(["triads", "imu2", "parameters", "gain", "value"], "big"),
                               "triads.imu2.parameters.gain"),
    "parameter_value_misshaped": (_results_edit(["triads", "imu2", "parameters", "bias", "value"], [1, 2]),
                                  "triads.imu2.parameters.bias"),
    "parameters_not_a_mapping": (_results_edit(["triads", "imu2", "parameters"], [1, 2, 3]), "triads.imu2.parameters"),
    "R_nominal_missing": (_results_edit(["triads", "imu2", "R_nominal"], KeyError), "triads.imu2.R_nominal"),
    "R_nominal_misshaped": (_results_edit(["triads", "imu2", "R_nominal"], [[1, 0], [0, 1]]), "triads.imu2.R_nominal"),
    "status_missing": (_results_edit(["status"], KeyError), "status"),
    "residuals_not_numeric": (_results_edit(["residuals", "chi2_per_dof"], "many"), "residuals.chi2_per_dof"),
    "effects_not_a_mapping": (_results_edit(["effects"], "all"), "effects"),
}

for _name, (_edit, _key) in RESULTS_DEFECTS.items():
    def _apply_case(base, tmp, _edit=_edit, _key=_key):
        d = solved_copy(base, tmp, "static_solved", results=_edit)
        return Spec(["apply", str(d / "results.json"), str(base / "static" / "data.csv"), "-o", str(tmp / "o.csv")],
                    2, ("results.json", _key))

    def _report_case(base, tmp, _edit=_edit, _key=_key):
        d = solved_copy(base, tmp, "static_solved", results=_edit)
        return Spec(["report", str(d)], 2, ("results.json", _key))

    CASES.append(Case(f"apply_results_{_name}", "traceback", _apply_case))
    CASES.append(Case(f"report_results_{_name}", "traceback" if _name != "status_missing" else "silent",
                      _report_case))


DETAILS_DEFECTS = {
    "residual_acc_misshaped": (lambda a: a.update(residual_acc=np.zeros((2, 2))), "residual_acc"),
    "acc_sigma_strings": (lambda a: a.update(acc_sigma=np.array(["a", "b"])), "acc_sigma"),
    "norm_error_missing": (lambda a: a.pop("norm_error_after"), "norm_error_after"),
    "triads_mismatch": (lambda a: a.update(triads=np.array(["x", "y"])), "triads"),
}
for _name, (_edit, _key) in DETAILS_DEFECTS.items():
    def _details_case(base, tmp, _edit=_edit, _key=_key):
        d = solved_copy(base, tmp, "static_solved", details=_edit)
        return Spec(["report", str(d)], 2, ("details.npz", _key))
    CASES.append(Case(f"report_details_{_name}", "traceback", _details_case))


@case("traceback")
def report_dynamic_details_misshaped(base, tmp):
    d = solved_copy(base, tmp, "dyn_solved", details=lambda a: a.update(omega=np.zeros((3,))))
    return Spec(["report", str(d)], 2, ("details.npz", "omega"))


@case("traceback")
def scenario_unbounded_samples(base, tmp):
    p = tmp / "scenario.yaml"
    p.write_text("kind: dynamic_array\ngeometry: carlsson\nsamples: 100000000000\n")
    return Spec(["simulate", str(p), "-o", str(tmp / "out")], 2, ("scenario.yaml", "samples"))


@case("traceback")
def scenario_unbounded_time_series(base, tmp):
    p = tmp / "scenario.yaml"
    p.write_text("kind: static_array\ntriads: 3\ntime_series: true\nrate: 1000000\npose_duration: 100000\n")
    return Spec(["simulate", str(p), "-o", str(tmp / "out")], 2, ("scenario.yaml",))


@case("traceback")
def scenario_unbounded_triads(base, tmp):
    p = tmp / "scenario.yaml"
    p.write_text("kind: static_array\ntriads: 100000000\n")
    return Spec(["simulate", str(p), "-o", str(tmp / "out")], 2, ("scenario.yaml", "triads"))


@case("traceback")
def scenario_unbounded_poses(base, tmp):
    p = tmp / "scenario.yaml"
    p.write_text("kind: static_array\ntriads: 3\nposes: 1000000000\n")
    return Spec(["simulate", str(p), "-o", str(tmp / "out")], 2, ("scenario.yaml", "poses"))


# ---------------------------------------------------------------- silent wrong answers


@case("silent")
def problem_duplicate_key(base, tmp):
    text = (base / "rows" / "problem.yaml").read_text().replace("  gravity: 9.81", "  gravity: 9.81\n  gravity: 9.0")
    (tmp / "data.csv").symlink_to(base / "rows" / "data.csv")
    p = tmp / "problem.yaml"
    p.write_text(text)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "model.gravity", "duplicate"))


@case("silent")
def problem_duplicate_top_key(base, tmp):
    text = (base / "rows" / "problem.yaml").read_text() + "kind: dynamic_array\n"
    (tmp / "data.csv").symlink_to(base / "rows" / "data.csv")
    p = tmp / "problem.yaml"
    p.write_text(text)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "kind", "duplicate"))


@case("silent")
def scenario_duplicate_key(base, tmp):
    p = tmp / "scenario.yaml"
    p.write_text("kind: static_array\ntriads: 3\nseed: 1\nseed: 2\n")
    return Spec(["simulate", str(p), "-o", str(tmp / "out")], 2, ("scenario.yaml", "seed", "duplicate"))


@case("silent")
def csv_acc_in_g_declared_si(base, tmp):
    rec = load_rec(base)
    p = with_data(base, tmp, edited(rec, acc={n: a / G for n, a in rec.acc.items()}))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.units.accelerometer", "g"))


@case("silent")
def csv_acc_in_si_declared_g(base, tmp):
    rec = load_rec(base)
    doc = static_problem("data.csv", "csv", rec.triads)
    doc["data"]["units"] = {"accelerometer": "g"}
    p = with_data(base, tmp, rec, problem=doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.units.accelerometer", "m/s^2"))


@case("silent")
def npz_acc_in_g_declared_si(base, tmp):
    rec = load_rec(base)
    p = with_data(base, tmp, edited(rec, acc={n: a / G for n, a in rec.acc.items()}), fmt="npz")
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.units.accelerometer",))


@case("silent")
def imutk_acc_scale_wrong_by_g(base, tmp):
    doc = yaml.safe_load((base / "imutk.yaml").read_text())
    doc["data"]["units"]["accelerometer"] = {**IMUTK_ACC, "scale_unit": "g"}
    doc["data"]["path"], doc["data"]["gyro_path"] = str(base / "acc.mat"), str(base / "gyro.mat")
    p = write_yaml(tmp / "problem.yaml", doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.units.accelerometer",))


@case("silent")
def imutk_gyro_path_is_the_accelerometer_table(base, tmp):
    """data.gyro_path naming the accelerometer table itself: its gravity was fitted as angular rates
    (on the Xsens session a gyroscope bias of 0.10-0.12 rad/s) and the solve succeeded."""
    doc = yaml.safe_load((base / "imutk.yaml").read_text())
    doc["data"]["path"] = doc["data"]["gyro_path"] = str(base / "acc.mat")
    p = write_yaml(tmp / "problem.yaml", doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.gyro_path", "is data.path itself (acc.mat)"))


@case("silent")
def apply_gyro_is_the_data_file(base, tmp):
    """apply --gyro naming DATA itself: the accelerometer table was read as the gyroscope's too and
    written as calibrated rates."""
    return Spec(["apply", str(base / "imutk_solved" / "results.json"), str(base / "acc.mat"), "--format", "imutk",
                 "--gyro", str(base / "acc.mat"), "-o", str(tmp / "out.csv")], 2, ("--gyro", "is DATA itself (acc.mat)"))


@case("silent")
def mimu_acc_units_declared_si(base, tmp):
    doc = yaml.safe_load((base / "mimu.yaml").read_text())
    doc["data"]["path"] = str(base / "mimu.bin")
    doc["data"]["units"] = {"accelerometer": {"unit": "counts", "scale": 1 / 2048}}  # counts -> g, said m/s^2
    p = write_yaml(tmp / "problem.yaml", doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.units.accelerometer",))


@case("silent")
def csv_gyro_in_deg_declared_rad(base, tmp):
    rec = load_rec(base)
    p = with_data(base, tmp, edited(rec, gyro={n: np.degrees(a) for n, a in rec.gyro.items()}))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.units.gyroscope", "deg/s"))


@case("silent")
def dynamic_gyro_in_deg_declared_rad(base, tmp):
    rec = read_csv(base / "dyn" / "data.csv")
    doc = problem_doc(base, "dyn")
    p = with_data(base, tmp, edited(rec, gyro={n: np.degrees(a) for n, a in rec.gyro.items()}), problem=doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.units.gyroscope", "deg/s"))


@case("silent")
def dynamic_accelerometers_negative_units_scale(base, tmp):
    """Every accelerometer read with reversed sign by a negative data.units scale: the fit mirrored every
    position through the reference triad (χ²/dof 1.05, success, 1500σ from the truth); refused when read,
    as in the static kind (a static fit cannot see it)."""
    p = problem_in(base, tmp, "dyn", lambda d: d["data"].update(units={"accelerometer": {"unit": "counts", "scale": -1.0}}))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2,
                ("problem.yaml", "data.units.accelerometer.scale", "expected a positive scale", "found -1.0"))


@case("silent")
def dynamic_accelerometers_negated_columns(base, tmp):
    """Every accelerometer column negated in the data file: the fit mirrors every position (check_mirrored)."""
    rec = read_csv(base / "dyn" / "data.csv")
    p = with_data(base, tmp, edited(rec, acc={n: -a for n, a in rec.acc.items()}), problem=problem_doc(base, "dyn"))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2,
                ("problem.yaml", "array.triads", "opposite their nominal positions", "reversed sign"))


@case("silent")
def static_accelerometers_negative_units_scale(base, tmp):
    """A negative data.units scale mirrors every triad, which static poses cannot show: the fit had the same
    χ²/dof (0.987), positive gains and success, with every pose direction and the calibration reflected."""
    p = problem_in(base, tmp, "rows", lambda d: d["data"].update(units={"accelerometer": {"unit": "counts", "scale": -1.0}}))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2,
                ("problem.yaml", "data.units.accelerometer.scale", "expected a positive scale", "found -1.0"))


@case("silent")
def static_gyroscope_negative_units_scale_one_axis(base, tmp):
    p = problem_in(base, tmp, "static", lambda d: d["data"].update(
        units={"gyroscope": {"unit": "counts", "scale": [1.0, -1.0, 1.0]}}))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2,
                ("problem.yaml", "data.units.gyroscope.scale", "expected a positive scale", "found [1.0, -1.0, 1.0]"))


#: A Schopp board (5 triads) with gyroscopes and the default process model, 300 samples of sinusoids to 10 rad/s.
SCHOPP_GYRO = ("kind: dynamic_array\nseed: 2016\ngeometry: schopp\nsamples: 300\ngyroscope: true\nrate: 125\n"
               "trajectory: sinusoids\nmax_omega: 573\nmax_omega_dot: 8594\nnoise: {accelerometer: 0.02}\n"
               "position_error: 0.001\norientation_error: 0.5\n")


@case("silent")
def dynamic_one_gyroscope_axis_reversed_process_model(base, tmp):
    """acc3.gx read with reversed sign, process model on: the fit passed (χ²/dof 0.85 at 675 samples, the
    misfit taken by a motion-dependent gyroscope noise floor of 1.12 rad/s, the bias 0.23 ± 1 rad/s inside its
    range, positions on their side), with only the lag-1 autocorrelation warning that correct data give too.
    Refused before the solve: the axis's readings correlate with the other triads' gyroscopes at -0.9999 (with
    the fit's prediction of them, the check after the solve, at -0.9999 too); correct axes at +0.999."""
    (tmp / "sim").mkdir()
    (tmp / "sim" / "scenario.yaml").write_text(SCHOPP_GYRO)
    cli("simulate", tmp / "sim" / "scenario.yaml", "-o", tmp / "sim")
    rec = read_csv(tmp / "sim" / "data.csv")
    gyro = {**rec.gyro, "acc3": rec.gyro["acc3"] * np.array([-1.0, 1.0, 1.0])}
    p = with_data(base, tmp, edited(rec, gyro=gyro), problem=problem_doc(tmp, "sim"))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2,
                ("data.csv", "acc3.gx", "against the other triads' gyroscopes", "expected a positive gain",
                 "reversed sign"))


@case("silent")
def dynamic_one_gyroscope_reversed(base, tmp):
    """imu11's gyroscope read with reversed sign: the fit explained it by gyroscope biases of 7-40 rad/s
    (χ²/dof 1.04 after the motion-dependent noise fitted a 7 rad/s floor; positions 13-21 mm, 5σ, off), which
    the bias range then refused; now refused before the solve, against the other triads' gyroscopes."""
    rec = read_csv(base / "dyn" / "data.csv")
    p = with_data(base, tmp, edited(rec, gyro={n: -a if n == "imu11" else a for n, a in rec.gyro.items()}),
                  problem=problem_doc(base, "dyn"))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2,
                ("data.csv", "imu11.g", "against the other triads' gyroscopes", "reversed sign"))


@case("silent")
def dynamic_reference_gyroscope_axis_reversed(base, tmp):
    """The reference triad's gyroscope z axis read with reversed sign: its gain and alignment are fixed, so
    no estimate can take the sign. On the real MIMU4444 exp_1 the first attempt ran 200 IPOPT iterations
    (218 s) to Maximum_Iterations_Exceeded, and the next attempts as long; refused before the solve (0.8 s
    there), its readings against the other triads' gyroscopes at -0.9998."""
    rec = read_csv(base / "dyn" / "data.csv")
    ref = problem_doc(base, "dyn")["array"]["reference"]
    gyro = {n: a * np.array([1.0, 1.0, -1.0]) if n == ref else a for n, a in rec.gyro.items()}
    p = with_data(base, tmp, edited(rec, gyro=gyro), problem=problem_doc(base, "dyn"))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2,
                ("data.csv", f"{ref}.gz", "against the other triads' gyroscopes", "reversed sign"))


def _mimu_with(base, tmp, mutate):
    rec = load_rec(base)
    parts = np.load(base / "mimu_parts.npy")
    ticks, counter = parts[:, 0].copy(), parts[:, 1].copy()
    mutate(ticks, counter)
    (tmp / "data.bin").write_bytes(mimu_stream(ticks, counter, mimu_values(rec, rec.triads[:2])))
    return tmp / "data.bin"


def _no_time_jump(path: Path, max_dt: float = 1.0):
    def check(res):
        t = read_csv(path).t
        if np.diff(t).max() > max_dt:
            return f"time jumps by {np.diff(t).max():.3f} s in the output"
        if "timestamp" not in (res["stderr"] + res["stdout"]).lower():
            return "repaired without a note"
        return None
    return check


@case("silent")
def mimu_timestamp_backwards(base, tmp):
    def mutate(ticks, counter):
        ticks[1500] -= 3 * round(64e6 / 50)  # one stamp 3 samples back; the counter is contiguous
    data = _mimu_with(base, tmp, mutate)
    out = tmp / "out.csv"
    return Spec(["apply", str(base / "mimu_solved" / "results.json"), str(data), "-o", str(out)], 0,
                output=out, check=_no_time_jump(out))


@case("silent")
def mimu_timestamp_jump_counter_contiguous(base, tmp):
    def mutate(ticks, counter):
        ticks[1500:] += 40 * 64_000_000  # 40 s jump with no packet missing
    data = _mimu_with(base, tmp, mutate)
    out = tmp / "out.csv"
    return Spec(["apply", str(base / "mimu_solved" / "results.json"), str(data), "-o", str(out)], 0,
                output=out, check=_no_time_jump(out))


@case("silent")
def mimu_timestamp_duplicated_different_packet(base, tmp):
    def mutate(ticks, counter):
        ticks[1500] = ticks[1499]  # same stamp, next counter: a stuck clock, not a repeated packet
    data = _mimu_with(base, tmp, mutate)
    out = tmp / "out.csv"

    def check(res):
        n = len(read_csv(out).t)
        if n != len(np.load(base / "mimu_parts.npy")):
            return f"{n} samples written; a packet with a new counter was dropped as a duplicate"
        return _no_time_jump(out)(res)
    return Spec(["apply", str(base / "mimu_solved" / "results.json"), str(data), "-o", str(out)], 0,
                output=out, check=check)


@case("silent")
def static_phase_given_to_dynamic_kind(base, tmp):
    """The static session (3 triads at rest, 12 poses) given to the dynamic kind with positions."""
    doc = problem_doc(base, "dyn")
    rec = load_rec(base)
    doc["array"]["triads"] = [{"name": n, "position": [0.0189 * i, 0.0, 0.0]} for i, n in enumerate(rec.triads)]
    doc["array"]["reference"] = rec.triads[0]
    p = with_data(base, tmp, rec, problem=doc)
    # the whole recording (no data.time_range in the file): its time column and sample count are named
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.csv: t:", "samples", "angular"))


@case("silent")
def dynamic_little_rotation(base, tmp):
    """A dynamic recording whose angular rate is 30x smaller: positions barely determined."""
    (tmp / "sc.yaml").write_text("kind: dynamic_array\ngeometry: carlsson\nimus: 4\nsamples: 200\nseed: 3\n"
                                 "max_omega: 20\nmax_omega_dot: 20\n")
    res = run_cli(["simulate", str(tmp / "sc.yaml"), "-o", str(tmp / "sim")])
    assert res["rc"] == 0, res
    return Spec(["solve", str(tmp / "sim" / "problem.yaml"), "-o", str(tmp / "out"), "-q"], 2,
                ("data.csv: t:", "200 samples", "angular"))  # the whole recording: its time column named


@case("silent")
def report_results_no_parameters(base, tmp):
    def edit(doc):
        for t in doc["triads"].values():
            t.pop("parameters")
    d = solved_copy(base, tmp, "static_solved", results=edit)
    return Spec(["report", str(d)], 2, ("results.json", "parameters"))


@case("silent")
def report_results_status_not_numeric(base, tmp):
    d = solved_copy(base, tmp, "static_solved", results=_results_edit(["status", "success"], "yes"))
    return Spec(["report", str(d)], 2, ("results.json", "status.success"))


# ---------------------------------------------------------------- touched inputs, partial outputs


@case("touched")
def apply_output_equals_input(base, tmp):
    data = copy(base / "static" / "data.csv", tmp)
    return Spec(["apply", str(base / "static_solved" / "results.json"), str(data), "-o", str(data)], 2,
                ("data.csv", "input"))


@case("touched")
def apply_output_equals_input_other_spelling(base, tmp):
    data = copy(base / "static" / "data.csv", tmp)
    (tmp / "sub").mkdir()
    return Spec(["apply", str(base / "static_solved" / "results.json"), str(data), "-o",
                 str(tmp / "sub" / ".." / "data.csv")], 2, ("data.csv", "input"))


@case("touched")
def apply_output_equals_input_npz(base, tmp):
    data = copy(base / "static.npz", tmp)
    return Spec(["apply", str(base / "static_solved" / "results.json"), str(data), "-o", str(data)], 2,
                ("static.npz", "input"))


@case("touched")
def solve_partial_output(base, tmp):
    out = tmp / "out"
    (out / "results.json").mkdir(parents=True)
    return Spec(["solve", str(base / "rows" / "problem.yaml"), "-o", str(out), "-q"], 2, ("results.json",))


@case("touched")
def solve_output_overwrites_intrinsics(base, tmp):
    """A dynamic problem whose model.intrinsics is DIR/results.json, solved into DIR."""
    shutil.copytree(base / "dyn_solved", tmp / "run")
    doc = problem_doc(base, "dyn")
    doc["data"]["path"] = str(base / "dyn" / "data.csv")
    doc["model"]["intrinsics"] = "run/results.json"
    # the intrinsics' triads must be those of the problem: use the static session's names
    p = write_yaml(tmp / "problem.yaml", doc)
    return Spec(["solve", str(p), "-o", str(tmp / "run"), "-q"], 2, ("results.json", "input"))


@case("touched")
def simulate_output_overwrites_scenario(base, tmp):
    p = tmp / "problem.yaml"
    p.write_text("kind: static_array\ntriads: 3\nposes: 20\nseed: 2\n")
    return Spec(["simulate", str(p), "-o", str(tmp)], 2, ("problem.yaml", "input"))


@case("touched")
def solve_output_overwrites_data(base, tmp):
    """The problem reads DIR/details.npz as its data (npz); solving into DIR would replace it."""
    (tmp / "details.npz").write_bytes((base / "static.npz").read_bytes())
    rec = load_rec(base)
    p = write_yaml(tmp / "problem.yaml", static_problem("details.npz", "npz", rec.triads))
    return Spec(["solve", str(p), "-o", str(tmp), "-q"], 2, ("details.npz", "input"))


@case("touched")
def codegen_output_overwrites_data(base, tmp):
    """The problem's data file (csv, whatever its name) is DIR/test_vectors.txt, a file codegen writes;
    only the problem file itself was kept from the outputs."""
    out = tmp / "c"
    out.mkdir()
    copy(base / "rows" / "data.csv", out, "test_vectors.txt")
    doc = problem_doc(base, "rows")
    doc["data"]["path"] = str(out / "test_vectors.txt")
    p = write_yaml(tmp / "problem.yaml", doc)
    return Spec(["codegen", str(p), "-o", str(out), "-q"], 2, ("test_vectors.txt", "input"))


@case("touched")
def apply_output_overwrites_the_imutk_gyroscope_beside_the_data(base, tmp):
    """imu_tk data acc.csv read with its gyroscope gyro.csv beside it (found by name, no --gyro):
    -o gyro.csv would replace that input."""
    data = copy(base / "acc.mat", tmp, "acc.csv")
    copy(base / "gyro.mat", tmp, "gyro.csv")
    return Spec(["apply", str(base / "imutk_solved" / "results.json"), str(data), "--format", "imutk", "-o",
                 str(tmp / "gyro.csv")], 2, ("gyro.csv", "input"))


@case("touched")
def batch_output_overwrites_the_templates_intrinsics(base, tmp):
    """A batch template whose model.intrinsics is DIR/<recording>/results.json, batched into DIR: the
    recording's results.json would replace it (refused before the cluster starts)."""
    (tmp / "out" / "data").mkdir(parents=True)
    shutil.copyfile(base / "rows_solved" / "results.json", tmp / "out" / "data" / "results.json")
    doc = problem_doc(base, "rows")
    doc["model"]["intrinsics"] = "out/data/results.json"
    p = write_yaml(tmp / "template.yaml", doc)
    return Spec(["batch", str(p), str(base / "rows" / "data.csv"), "-o", str(tmp / "out"), "--workers", "1", "-q"],
                2, ("results.json", "input"))


@case("touched")
def diagnose_into_the_problem_directory(base, tmp):
    """diagnose writing beside its own problem and data: the inputs stay as they were."""
    (tmp / "data.csv").write_bytes((base / "rows" / "data.csv").read_bytes())
    p = copy(base / "rows" / "problem.yaml", tmp, "x.yaml")
    return Spec(["diagnose", str(p), "-o", str(tmp), "-q"], 0, output=tmp)


# ---------------------------------------------------------------- vague refusals


@case("vague")
def clipped_channel(base, tmp):
    rec = load_rec(base)
    acc = dict(rec.acc)
    a = acc["imu2"].copy()
    a[:, 0] = np.minimum(a[:, 0], 2.0)  # x axis clipped at +2 m/s^2 (a rail)
    acc["imu2"] = a
    p = with_data(base, tmp, edited(rec, acc=acc))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("imu2.ax",))


@case("vague")
def stuck_channel(base, tmp):
    rec = load_rec(base)
    acc = dict(rec.acc)
    a = acc["imu3"].copy()
    a[:, 2] = 4.2
    acc["imu3"] = a
    p = with_data(base, tmp, edited(rec, acc=acc))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("imu3.az",))


@case("vague")
def all_zero_triad(base, tmp):
    rec = load_rec(base)
    acc = dict(rec.acc)
    acc["imu2"] = np.zeros_like(acc["imu2"])
    p = with_data(base, tmp, edited(rec, acc=acc))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("imu2",))


@case("vague")
def all_zero_triad_rows(base, tmp):
    rec = read_csv(base / "rows" / "data.csv")
    acc = dict(rec.acc)
    acc["imu3"] = np.zeros_like(acc["imu3"])
    doc = problem_doc(base, "rows")
    p = with_data(base, tmp, edited(rec, acc=acc), problem=doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("imu3",))


@case("vague")
def fully_masked_gyroscope(base, tmp):
    p = problem_in(base, tmp, "dyn", lambda d: d["data"].update(saturation={"gyroscope": 1e-6}))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.saturation.gyroscope",))


@case("vague")
def gravity_absurd(base, tmp):
    p = problem_in(base, tmp, "rows", lambda d: d["model"].update(gravity=1e308))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("model.gravity",))


@case("vague")
def sigma_absurd(base, tmp):
    p = problem_in(base, tmp, "rows", lambda d: d["noise"].update(accelerometer=1e300))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("noise.accelerometer",))


@case("vague")
def sigma_tiny(base, tmp):
    p = problem_in(base, tmp, "rows", lambda d: d["noise"].update(accelerometer=1e-300))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("noise.accelerometer",))


@case("vague")
def detection_window_absurd(base, tmp):
    p = problem_in(base, tmp, "static", lambda d: d["data"].update(detection={"window": 1e300}))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.detection.window",))


@case("vague")
def scenario_noise_absurd(base, tmp):
    p = tmp / "scenario.yaml"
    p.write_text("kind: static_array\ntriads: 3\nnoise: {accelerometer: 1.0e+300}\n")
    return Spec(["simulate", str(p), "-o", str(tmp / "out")], 2, ("scenario.yaml", "noise.accelerometer"))


@case("vague")
def units_scale_absurd(base, tmp):
    p = problem_in(base, tmp, "static", lambda d: d["data"].update(units={"accelerometer": {"unit": "counts",
                                                                                       "scale": 1e300}}))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.units.accelerometer",))


for _fmt, _make in {
    "csv": lambda base, tmp: problem_in(base, tmp, "static", lambda d: d["data"].update(path=str(tmp / "dir"))),
    "npz": lambda base, tmp: write_yaml(tmp / "problem.yaml", {**yaml.safe_load((base / "npz.yaml").read_text()),
                                                               "data": {"path": str(tmp / "dir"), "format": "npz"}}),
    "mimu": lambda base, tmp: write_yaml(tmp / "problem.yaml", {**yaml.safe_load((base / "mimu.yaml").read_text()),
                                                                "data": {"path": str(tmp / "dir"), "format": "mimu"}}),
    "imutk": lambda base, tmp: write_yaml(tmp / "problem.yaml", {
        **yaml.safe_load((base / "imutk.yaml").read_text()),
        "data": {"path": str(base / "acc.mat"), "gyro_path": str(tmp / "dir"), "format": "imutk",
                 "units": {"accelerometer": IMUTK_ACC, "gyroscope": IMUTK_GYRO}}}),
}.items():
    def _dir_case(base, tmp, _make=_make, _fmt=_fmt):
        (tmp / "dir").mkdir()
        p = _make(base, tmp)
        key = "data.gyro_path" if _fmt == "imutk" else "data.path"
        return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, (key, "is a directory"))
    CASES.append(Case(f"{_fmt}_data_path_is_a_directory", "vague", _dir_case))


@case("vague")
def apply_data_is_a_directory(base, tmp):
    (tmp / "d.csv").mkdir()
    return Spec(["apply", str(base / "static_solved" / "results.json"), str(tmp / "d.csv"), "-o",
                 str(tmp / "o.csv")], 2, ("d.csv", "is a directory"))


@case("vague")
def report_dir_is_a_file(base, tmp):
    return Spec(["report", str(base / "rows_solved" / "results.json")], 2, ("results.json", "found a file"))


@case("vague")
def codegen_start_beyond_data(base, tmp):
    p = problem_in(base, tmp, "dyn", lambda d: d.update(motion={"process_model": False}))  # the C solver's motion
    return Spec(["codegen", str(p), "-o", str(tmp / "out"), "--window", "50", "--start", "1000000"], 2,
                ("--start", "200"))


@case("traceback")
def codegen_window_of_one_sample_with_a_process_model(base, tmp):
    """An internal LinAlgError from the reference solve's covariance (the nuisance variables not determined)."""
    return Spec(["codegen", str(base / "dyn" / "problem.yaml"), "-o", str(tmp / "out"), "--window", "1"], 2,
                ("problem.yaml", "motion.process_model", "expected process_model: false, found true"))


@case("vague")
def codegen_negative_window(base, tmp):
    return Spec(["codegen", str(base / "dyn" / "problem.yaml"), "-o", str(tmp / "out"), "--window", "-5"], 2,
                ("--window",))


@case("vague")
def codegen_window_on_results(base, tmp):
    return Spec(["codegen", str(base / "rows_solved" / "results.json"), "-o", str(tmp / "out"), "--start", "3"], 2,
                ("--start",))


# ---------------------------------------------------------------- CLI (issue 14) and per-reader basics


@case("cli")
def solve_on_a_scenario_file(base, tmp):
    return Spec(["solve", str(base / "rows.yaml"), "-o", str(tmp / "out"), "-q"], 2, ("rows.yaml", "simulate"))


@case("cli")
def diagnose_on_a_scenario_file(base, tmp):
    return Spec(["diagnose", str(base / "rows.yaml"), "-o", str(tmp / "out"), "-q"], 2, ("rows.yaml", "simulate"))


@case("cli")
def simulate_on_a_problem_file(base, tmp):
    return Spec(["simulate", str(base / "rows" / "problem.yaml"), "-o", str(tmp / "out")], 2,
                ("problem.yaml", "solve"))


@case("cli")
def csv_reader_ok(base, tmp):
    return Spec(["solve", str(base / "static" / "problem.yaml"), "-o", str(tmp / "out"), "-q"], 0,
                output=tmp / "out")


@case("cli")
def npz_reader_ok(base, tmp):
    return Spec(["solve", str(base / "npz.yaml"), "-o", str(tmp / "out"), "-q"], 0, output=tmp / "out")


@case("cli")
def mimu_reader_ok_with_genuine_wrap(base, tmp):
    out = tmp / "out"

    def check(res):
        doc = json.loads((out / "results.json").read_text())
        if doc["poses"]["count"] != 12:
            return f"{doc['poses']['count']} poses found, expected 12"
        return None
    return Spec(["solve", str(base / "mimu.yaml"), "-o", str(out), "-q"], 0, output=out, check=check)


@case("cli")
def imutk_reader_ok(base, tmp):
    return Spec(["solve", str(base / "imutk.yaml"), "-o", str(tmp / "out"), "-q"], 0, output=tmp / "out")


@case("cli")
def mimu_truncated_stream(base, tmp):
    (tmp / "data.bin").write_bytes((base / "mimu.bin").read_bytes()[:20])
    doc = yaml.safe_load((base / "mimu.yaml").read_text())
    doc["data"]["path"] = "data.bin"
    p = write_yaml(tmp / "problem.yaml", doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.bin",))


@case("cli")
def npz_not_an_archive(base, tmp):
    (tmp / "data.npz").write_bytes(b"PK\x03\x04 not really")
    doc = yaml.safe_load((base / "npz.yaml").read_text())
    doc["data"]["path"] = "data.npz"
    p = write_yaml(tmp / "problem.yaml", doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.npz",))


@case("cli")
def imutk_binary_table(base, tmp):
    (tmp / "acc.mat").write_bytes(b"\x00\xff" * 100)
    doc = yaml.safe_load((base / "imutk.yaml").read_text())
    doc["data"].update(path="acc.mat", gyro_path=str(base / "gyro.mat"))
    p = write_yaml(tmp / "problem.yaml", doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("acc.mat",))


@case("cli")
def csv_not_utf8(base, tmp):
    (tmp / "data.csv").write_bytes(b"t,imu1.ax\n\xff\xfe\n")
    p = problem_in(base, tmp, "static", lambda d: d["data"].update(path="data.csv"))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.csv", "UTF-8"))


@case("cli")
def apply_ok_then_report_ok(base, tmp):
    out = tmp / "o.npz"
    return Spec(["apply", str(base / "static_solved" / "results.json"), str(base / "static.npz"), "-o", str(out)],
                0, output=out)


@case("cli")
def codegen_results_ok(base, tmp):
    return Spec(["codegen", str(base / "rows_solved" / "results.json"), "-o", str(tmp / "c")], 0,
                output=tmp / "c")


@case("cli")
def report_ok(base, tmp):
    d = solved_copy(base, tmp)
    return Spec(["report", str(d)], 0, output=d / "report.html")


# ============================================================================ surfaces added after the first sweep
# (the noise verb, the ferraris kind, the static kind's gyroscope from transitions, report -o, apply --gyro,
# model.intrinsics / model.reuse, the chip-clock and coupling effects, solver.elimination)


def ferraris_doc(path: str = "session.csv", sections: str = "sections.json", **data) -> dict:
    return {"kind": "ferraris", "data": {"path": path, "format": "imucal", "rate": 102.4, "sections": sections, **data},
            "array": {"reference": "imu", "triads": [{"name": "imu"}]}}


def ferraris_in(base: Path, tmp: Path, table: str | bytes | None = None, sections=None, **data) -> Path:
    """A Ferraris problem in tmp: base's session and section list unless replaced (text, bytes or a dict)."""
    if table is None:
        tp = str(base / "ferraris" / "session.csv")
    else:
        tp = "session.csv"
        (tmp / tp).write_bytes(table if isinstance(table, bytes) else table.encode())
    if sections is None:
        sp = str(base / "ferraris" / "sections.json")
    else:
        sp = "sections.json"
        (tmp / sp).write_bytes(sections if isinstance(sections, bytes) else
                               (sections if isinstance(sections, str) else json.dumps(sections)).encode())
    return write_yaml(tmp / "problem.yaml", ferraris_doc(tp, sp, **data))


def ferraris_sections(base: Path) -> dict:
    return json.loads((base / "ferraris" / "sections.json").read_text())


def ferraris_table(base: Path, edit: Callable[[dict], None]) -> str:
    """base's imucal table with its columns edited ({name: ndarray})."""
    lines = (base / "ferraris" / "session.csv").read_text().splitlines()
    names = lines[0].split(",")
    a = np.array([[float(x) for x in ln.split(",")] for ln in lines[1:]])
    cols = {n: a[:, i].copy() for i, n in enumerate(names)}
    edit(cols)
    names = list(cols)
    rows = np.column_stack([cols[n] for n in names])
    return ",".join(names) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n"


def _ferraris_solve(base, tmp, names, **kw):
    p = ferraris_in(base, tmp, **kw)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml",) + tuple(names))


def _sections_edit(edit, names):
    def build(base, tmp):
        sec = ferraris_sections(base)
        edit(sec)
        p = ferraris_in(base, tmp, sections=sec)
        return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("sections.json",) + tuple(names))
    return build


def _swap(a, b):
    def edit(sec):
        sec[a], sec[b] = sec[b], sec[a]
    return edit


FERRARIS_SECTIONS = {
    "missing_label": (lambda s: s.pop("z_rot"), ("z_rot",)),
    "start_a_string": (lambda s: s["x_p"].update(start="10"), ("x_p",)),
    "start_a_float": (lambda s: s["x_p"].update(start=10.5), ("x_p",)),
    "start_a_bool": (lambda s: s["x_p"].update(start=True), ("x_p",)),
    "end_before_start": (lambda s: s["y_a"].update(end=s["y_a"]["start"]), ("y_a",)),
    "end_beyond_data": (lambda s: s["z_rot"].update(end=10 ** 7), ("z_rot",)),
    "start_negative": (lambda s: s["x_a"].update(start=-5), ("x_a",)),
    "huge_integer": (lambda s: s["x_a"].update(end=10 ** 40), ("x_a",)),
    "not_a_mapping": (lambda s: s.update(x_p=[0, 10]), ("x_p",)),
    "face_too_short": (lambda s: s["z_p"].update(end=s["z_p"]["start"] + 1), ("z_p",)),
    "faces_swapped": (_swap("x_p", "x_a"), ("x_p",)),
    "face_on_a_turn": (lambda s: s.update(y_p=dict(s["x_rot"])), ("y_p",)),
    "turns_swapped": (_swap("x_rot", "y_rot"), ("x_rot",)),
    "turn_without_rotation": (lambda s: s.update(z_rot=dict(s["z_p"])), ("z_rot",)),
    # both silently accepted before: an extra label ignored, a face averaged over its neighbour's samples too
    "unknown_label": (lambda s: s.update(w_p={"start": 0, "end": 10}), ("w_p", "unknown section")),
    "overlapping": (lambda s: s["x_a"].update(start=s["x_p"]["end"] - 50), ("x_a", "overlap x_p")),
}
for _name, (_edit, _names) in FERRARIS_SECTIONS.items():
    CASES.append(Case(f"ferraris_sections_{_name}", "ferraris", _sections_edit(_edit, _names)))

FERRARIS_SECTION_FILES = {
    "empty": (b"", ()),
    "truncated": (b'{"x_p": {"start": 10, "e', ("line",)),
    "a_list": (b"[1, 2, 3]", ("mapping",)),
    "not_utf8": (b'{"x_p\xff": {"start": 1, "end": 2}}', ("UTF-8",)),
    "nan": (b'{"x_p": {"start": NaN, "end": 2}}', ("x_p",)),
}
for _name, (_raw, _names) in FERRARIS_SECTION_FILES.items():
    def _sec_file(base, tmp, _raw=_raw, _names=_names):
        p = ferraris_in(base, tmp, sections=_raw)
        return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("sections.json",) + _names)
    CASES.append(Case(f"ferraris_section_file_{_name}", "ferraris", _sec_file))


def _cols(fn):
    return lambda base, tmp: ferraris_table(base, fn)


FERRARIS_TABLES = {
    "empty": (lambda base, tmp: "", ("session.csv",)),
    "header_only": (lambda base, tmp: (base / "ferraris" / "session.csv").read_text().splitlines()[0] + "\n",
                    ("session.csv",)),
    "missing_column": (_cols(lambda c: c.pop("acc_z")), ("session.csv", "acc_z")),
    "nan_cell": (_cols(lambda c: c["gyr_y"].__setitem__(300, np.nan)), ("session.csv", "gyr_y")),
    "inf_cell": (_cols(lambda c: c["acc_x"].__setitem__(5, np.inf)), ("session.csv", "acc_x")),
    "counter_backwards": (_cols(lambda c: c["n_samples"].__setitem__(50, 3)), ("session.csv", "n_samples")),
    "truncated_mid_row": (lambda base, tmp: (base / "ferraris" / "session.csv").read_text()[:5000],
                          ("session.csv",)),
    "binary": (lambda base, tmp: b"\x00\x01\x02" * 500, ("session.csv",)),
    "acc_in_g": (_cols(lambda c: [c.__setitem__(k, c[k] / G) for k in ("acc_x", "acc_y", "acc_z")]),
                 ("accelerometer",)),
    "gyro_in_rad": (_cols(lambda c: [c.__setitem__(k, np.radians(c[k])) for k in ("gyr_x", "gyr_y", "gyr_z")]),
                    ("data.units.gyroscope",)),
    "gyro_stuck": (_cols(lambda c: c.__setitem__("gyr_z", np.zeros_like(c["gyr_z"]))), ("session.csv", "gyr_z")),
    "gyro_sign_flipped": (_cols(lambda c: c.__setitem__("gyr_x", -c["gyr_x"])), ("x_rot", "gyr_x")),
    "gyro_scaled_tenfold": (_cols(lambda c: c.__setitem__("gyr_y", 10 * c["gyr_y"])), ("y_rot",)),
    "constant": (_cols(lambda c: [c.__setitem__(k, np.full_like(c[k], 1.0)) for k in c if k != "n_samples"]),
                 ("session.csv",)),
}
for _name, (_make, _names) in FERRARIS_TABLES.items():
    def _table_case(base, tmp, _make=_make, _names=_names):
        p = ferraris_in(base, tmp, table=_make(base, tmp))
        return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, _names)
    CASES.append(Case(f"ferraris_table_{_name}", "ferraris", _table_case))

FERRARIS_KEYS = {
    "rate_tenfold": ({"rate": 1024.0}, ("data.rate", "x_rot")),
    "rate_huge": ({"rate": 1e300}, ("data.rate",)),
    "rate_string": ({"rate": "fast"}, ("data.rate",)),
    "turn_angle_sign": ({"turn_angle_deg": 360}, ("data.turn_angle_deg",)),
    "turn_angle_huge": ({"turn_angle_deg": 1e300}, ("data.turn_angle_deg",)),
    "turn_angle_string": ({"turn_angle_deg": "-360"}, ("data.turn_angle_deg",)),
    "turn_angle_half": ({"turn_angle_deg": -180}, ("data.turn_angle_deg",)),
    "segments_rows": ({"segments": "rows"}, ("data.segments",)),
    "time_range_cuts_turns": ({"time_range": [0, 20]}, ("data.time_range",)),
    "sections_a_directory": ({"sections": "."}, ("data.sections", "directory")),
    "sections_a_device": ({"sections": "/dev/zero"}, ("data.sections", "regular file")),
    "sections_a_number": ({"sections": 5}, ("data.sections",)),
}
for _name, (_data, _names) in FERRARIS_KEYS.items():
    def _key_case(base, tmp, _data=_data, _names=_names):
        p = ferraris_in(base, tmp)
        doc = yaml.safe_load(p.read_text())
        doc["data"].update(_data)
        write_yaml(p, doc)
        return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml",) + _names)
    CASES.append(Case(f"ferraris_{_name}", "ferraris", _key_case))


@case("ferraris")
def ferraris_effect_not_for_kind(base, tmp):
    p = ferraris_in(base, tmp)
    doc = yaml.safe_load(p.read_text())
    doc["model"] = {"accelerometer": {"bias_drift": "free"}}
    write_yaml(p, doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "model.accelerometer.bias_drift"))


@case("ferraris")
def ferraris_triad_name_not_in_table(base, tmp):
    p = ferraris_in(base, tmp)
    doc = yaml.safe_load(p.read_text())
    doc["array"] = {"reference": "mtw", "triads": [{"name": "mtw"}]}
    write_yaml(p, doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "mtw"))


@case("ferraris")
def ferraris_gyroscope_false(base, tmp):
    p = ferraris_in(base, tmp)
    doc = yaml.safe_load(p.read_text())
    doc["array"]["triads"][0]["gyroscope"] = False
    write_yaml(p, doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "gyroscope"))


@case("ferraris")
def ferraris_gyro_noise_absurd(base, tmp):
    p = ferraris_in(base, tmp)
    doc = yaml.safe_load(p.read_text())
    doc["noise"] = {"gyroscope": 1e300}
    write_yaml(p, doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "noise.gyroscope"))


@case("ferraris")
def ferraris_solve_output_overwrites_sections(base, tmp):
    """The section list is named results.json in the output directory."""
    shutil.copyfile(base / "ferraris" / "sections.json", tmp / "results.json")
    p = write_yaml(tmp / "problem.yaml", ferraris_doc(str(base / "ferraris" / "session.csv"), "results.json"))
    return Spec(["solve", str(p), "-o", str(tmp), "-q"], 2, ("results.json", "input"))


@case("ferraris")
def ferraris_diagnose_refused(base, tmp):
    p = ferraris_in(base, tmp)
    return Spec(["diagnose", str(p), "-o", str(tmp / "out"), "-q"], 2, ("problem.yaml", "ferraris"))


@case("ferraris")
def ferraris_codegen_refused(base, tmp):
    p = ferraris_in(base, tmp)
    return Spec(["codegen", str(p), "-o", str(tmp / "out")], 2, ("problem.yaml", "ferraris"))


@case("ferraris")
def ferraris_ok(base, tmp):
    p = ferraris_in(base, tmp)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 0, output=tmp / "out")


@case("ferraris")
def ferraris_report_ok(base, tmp):
    shutil.copytree(base / "ferraris_solved", tmp / "s")
    for q in (tmp / "s").iterdir():
        q.chmod(0o644)
    return Spec(["report", str(tmp / "s")], 0, output=tmp / "s" / "report.html")


# ---------------------------------------------------------------- castimate noise


def _noise(base, tmp, p, names=(), rc=2, out=None):
    out = out or tmp / "out"
    return Spec(["noise", str(p), "-o", str(out), "-q"], rc, names, output=out if rc == 0 else None)


@case("noise")
def noise_ok(base, tmp):
    out = tmp / "out"

    def check(res):
        for n in ("imu1", "imu2", "imu3"):
            doc = yaml.safe_load((out / f"imu_{n}.yaml").read_text())
            vals = [v for v in doc.values() if isinstance(v, float)]
            if not vals or not all(np.isfinite(vals)) or not all(v > 0 for v in vals):
                return f"imu_{n}.yaml has {doc}"
        return None
    s = _noise(base, tmp, base / "static" / "problem.yaml", rc=0)
    s.check = check
    return s


@case("noise")
def noise_output_is_a_file(base, tmp):
    (tmp / "taken").write_text("a file\n")
    return _noise(base, tmp, base / "static" / "problem.yaml", (str(tmp / "taken"), "directory"), out=tmp / "taken")


@case("noise")
def noise_output_not_creatable(base, tmp):
    (tmp / "taken").write_text("a file\n")
    return _noise(base, tmp, base / "static" / "problem.yaml", (str(tmp / "taken"),), out=tmp / "taken" / "sub")


@case("noise")
def noise_output_slot_is_a_directory(base, tmp):
    (tmp / "out" / "imu_imu2.yaml").mkdir(parents=True)
    return _noise(base, tmp, base / "static" / "problem.yaml", ("imu_imu2.yaml", "directory"))


@case("noise")
def noise_output_overwrites_problem(base, tmp):
    """A one-triad problem file called imu.yaml, characterised into its own directory."""
    rec = load_rec(base)
    one = Recording(t=rec.t, acc={"imu1": rec.acc["imu1"]}, gyro={"imu1": rec.gyro["imu1"]}, source=rec.source)
    p = with_data(base, tmp, one)
    p.rename(tmp / "imu.yaml")
    return _noise(base, tmp, tmp / "imu.yaml", ("imu.yaml", "input"), out=tmp)


@case("noise")
def noise_output_overwrites_data(base, tmp):
    """Data in npz named noise.json's neighbour: the data file is DIR/allan.png."""
    rec = load_rec(base)
    one = Recording(t=rec.t, acc={"imu1": rec.acc["imu1"]}, gyro={"imu1": rec.gyro["imu1"]}, source=rec.source)
    write_npz(tmp / "allan.npz", one)
    (tmp / "allan.npz").rename(tmp / "allan.png")
    p = write_yaml(tmp / "problem.yaml", static_problem("allan.png", "npz", ["imu1"]))
    return _noise(base, tmp, p, ("allan.png", "input"), out=tmp)


@case("noise")
def noise_rows_refused(base, tmp):
    return _noise(base, tmp, base / "rows" / "problem.yaml", ("problem.yaml", "data.segments"))


@case("noise")
def noise_continuous_motion(base, tmp):
    return _noise(base, tmp, base / "dyn" / "problem.yaml", ("problem.yaml", "static"))


@case("noise")
def noise_no_gyroscope(base, tmp):
    rec = load_rec(base)
    p = with_data(base, tmp, edited(rec, gyro={}))
    return _noise(base, tmp, p, rc=0, out=tmp / "out")


@case("noise")
def noise_stuck_channel(base, tmp):
    rec = load_rec(base)
    gyro = dict(rec.gyro)
    g = gyro["imu2"].copy()
    g[:, 1] = 0.0
    gyro["imu2"] = g
    p = with_data(base, tmp, edited(rec, gyro=gyro))
    return _noise(base, tmp, p, ("imu2.gy",))


@case("noise")
def noise_quantised_channel(base, tmp):
    """A channel quantised far above its noise: the Allan deviation is the quantisation, not the sensor."""
    rec = load_rec(base)
    acc = dict(rec.acc)
    a = acc["imu1"].copy()
    a[:, 0] = np.round(a[:, 0] / 0.5) * 0.5
    acc["imu1"] = a
    p = with_data(base, tmp, edited(rec, acc=acc))
    return _noise(base, tmp, p, ("imu1.ax",))


@case("noise")
def noise_segments_beyond_data(base, tmp):
    p = problem_in(base, tmp, "static", lambda d: d["data"].update(segments=[[1000, 1010], [2000, 2030]]))
    return _noise(base, tmp, p, ("problem.yaml", "data.segments"))


@case("noise")
def noise_segments_too_short(base, tmp):
    p = problem_in(base, tmp, "static", lambda d: d["data"].update(segments=[[0.5, 0.6]]))
    return _noise(base, tmp, p, ("problem.yaml", "data.segments"))


@case("noise")
def noise_time_gap_inside_segment(base, tmp):
    """A 10 s gap in the time stamps inside a static pose: the segment is cut there (the Allan variance
    needs uniform sampling), with a note."""
    rec = load_rec(base)
    t = rec.t.copy()
    t[100:] += 10.0
    p = with_data(base, tmp, edited(rec, t=t))
    out = tmp / "out"
    return Spec(["noise", str(p), "-o", str(out)], 0, output=out,
                check=lambda res: None if "gap" in res["stderr"] else "segment with a gap used without a note")


@case("noise")
def noise_scenario_file(base, tmp):
    return _noise(base, tmp, base / "rows.yaml", ("rows.yaml", "simulate"))


@case("noise")
def noise_problem_is_a_device(base, tmp):
    return _noise(base, tmp, "/dev/zero", ("/dev/zero", "regular file"))


@case("noise")
def noise_acc_in_g(base, tmp):
    rec = load_rec(base)
    p = with_data(base, tmp, edited(rec, acc={n: a / G for n, a in rec.acc.items()}))
    return _noise(base, tmp, p, ("data.units.accelerometer",))


@case("noise")
def noise_gyro_in_deg(base, tmp):
    rec = load_rec(base)
    p = with_data(base, tmp, edited(rec, gyro={n: np.degrees(a) for n, a in rec.gyro.items()}))
    return _noise(base, tmp, p, ("data.units.gyroscope",))


@case("noise")
def noise_ferraris_problem(base, tmp):
    p = ferraris_in(base, tmp)
    return _noise(base, tmp, p, rc=0, out=tmp / "out")


@case("noise")
def noise_tiny_recording(base, tmp):
    rec = load_rec(base)
    p = with_data(base, tmp, rec.select(np.arange(len(rec.t)) < 8))
    return _noise(base, tmp, p, ("data.csv", "too few"))


@case("noise")
def noise_time_range_outside(base, tmp):
    p = problem_in(base, tmp, "static", lambda d: d["data"].update(time_range=[500, 600]))
    return _noise(base, tmp, p, ("problem.yaml", "data.time_range"))


@case("ferraris")
def ferraris_codegen_of_results(base, tmp):
    return Spec(["codegen", str(base / "ferraris_solved" / "results.json"), "-o", str(tmp / "c")], 0,
                output=tmp / "c")


@case("ferraris")
def ferraris_results_with_dynamic_details(base, tmp):
    """A Ferraris results.json beside a dynamic details.npz: the report names the mismatch."""
    d = tmp / "solved"
    d.mkdir()
    copy(base / "ferraris_solved" / "results.json", d)
    copy(base / "dyn_solved" / "details.npz", d)
    return Spec(["report", str(d)], 2, ("details.npz",))


@case("ferraris")
def report_results_unknown_kind(base, tmp):
    d = solved_copy(base, tmp, "static_solved", results=_results_edit(["kind"], "wobbly_array"))
    return Spec(["report", str(d)], 2, ("results.json", "kind", "wobbly_array"))


# ---------------------------------------------------------------- static kind: gyroscope from transitions


def _gyro_free(d):
    d.setdefault("model", {})["gyroscope"] = {"gain": "free", "misalignment": "free"}


def _transitions(base, tmp, rec=None, names=(), rc=2, edit=None):
    rec = rec if rec is not None else load_rec(base)
    doc = static_problem("data.csv", "csv", rec.triads)
    _gyro_free(doc)
    if edit:
        edit(doc)
    p = with_data(base, tmp, rec, problem=doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], rc, tuple(names),
                output=tmp / "out" if rc == 0 else None)


@case("transitions")
def transitions_ok(base, tmp):
    return _transitions(base, tmp, rc=0)


@case("transitions")
def transitions_no_gyroscope(base, tmp):
    rec = load_rec(base)
    return _transitions(base, tmp, edited(rec, gyro={}), ("problem.yaml", "model.gyroscope.gain", "imu1"))


@case("transitions")
def transitions_gyro_sign_flipped(base, tmp):
    rec = load_rec(base)
    gyro = dict(rec.gyro)
    gyro["imu2"] = gyro["imu2"] * np.array([1, -1, 1])
    return _transitions(base, tmp, edited(rec, gyro=gyro), ("imu2.gy",))


@case("transitions")
def transitions_gyro_in_deg(base, tmp):
    rec = load_rec(base)
    return _transitions(base, tmp, edited(rec, gyro={n: np.degrees(g) for n, g in rec.gyro.items()}),
                        ("data.units.gyroscope",))


@case("transitions")
def transitions_gyro_stuck(base, tmp):
    rec = load_rec(base)
    gyro = dict(rec.gyro)
    g = gyro["imu3"].copy()
    g[:, 2] = 0.001
    gyro["imu3"] = g
    return _transitions(base, tmp, edited(rec, gyro=gyro), ("imu3.gz",))


@case("transitions")
def transitions_time_gap(base, tmp):
    """A 60 s gap in the time stamps inside a transition: the rotation cannot be integrated across it."""
    rec = load_rec(base)
    t = rec.t.copy()
    # the first transition: after the first 4 s pose at 50 Hz
    t[220:] += 60.0
    return _transitions(base, tmp, edited(rec, t=t), ("data.csv", "gap"))


@case("transitions")
def transitions_explicit_segments_overlap(base, tmp):
    def edit(doc):
        doc["data"]["segments"] = [[0.5, 3.5], [3.0, 8.0], [10.5, 13.5]]
    return _transitions(base, tmp, names=("problem.yaml", "data.segments"), edit=edit)


@case("transitions")
def transitions_explicit_segments_unordered(base, tmp):
    def edit(doc):
        doc["data"]["segments"] = [[10.5, 13.5], [0.5, 3.5], [5.5, 8.5], [15.5, 18.5], [20.5, 23.5], [25.5, 28.5]]
    return _transitions(base, tmp, names=("problem.yaml", "data.segments", "time order"), edit=edit)


@case("transitions")
def transitions_gyro_noise_absurd(base, tmp):
    def edit(doc):
        doc["noise"]["gyroscope"] = 1e300
    return _transitions(base, tmp, names=("problem.yaml", "noise.gyroscope"), edit=edit)


@case("transitions")
def transitions_gyroscope_gain_bad_initial(base, tmp):
    def edit(doc):
        doc["model"]["gyroscope"]["gain"] = {"free": True, "initial": [1, 1]}
    return _transitions(base, tmp, names=("problem.yaml", "model.gyroscope.gain.initial"), edit=edit)


@case("transitions")
def transitions_gyroscope_gain_zero_initial(base, tmp):
    def edit(doc):
        doc["model"]["gyroscope"]["gain"] = {"free": True, "initial": 0}
    return _transitions(base, tmp, names=("problem.yaml", "model.gyroscope.gain.initial", "physical range"), edit=edit)


# ---------------------------------------------------------------- report -o, apply --gyro


@case("report_o")
def report_o_equals_results(base, tmp):
    d = solved_copy(base, tmp)
    return Spec(["report", str(d), "-o", str(d / "results.json")], 2, ("results.json", "input"))


@case("report_o")
def report_o_equals_details_other_spelling(base, tmp):
    d = solved_copy(base, tmp)
    (d / "sub").mkdir()
    return Spec(["report", str(d), "-o", str(d / "sub" / ".." / "details.npz")], 2, ("details.npz", "input"))


@case("report_o")
def report_o_is_a_directory(base, tmp):
    d = solved_copy(base, tmp)
    (tmp / "r.html").mkdir()
    return Spec(["report", str(d), "-o", str(tmp / "r.html")], 2, ("r.html", "directory"))


@case("report_o")
def report_o_not_creatable(base, tmp):
    d = solved_copy(base, tmp)
    (tmp / "taken").write_text("a file\n")
    return Spec(["report", str(d), "-o", str(tmp / "taken" / "r.html")], 2, (str(tmp / "taken"),))


@case("report_o")
def report_o_a_fifo(base, tmp):
    """An output that is not a regular file (a FIFO here; a device such as /dev/null was replaced by a
    regular file when run as root) is refused, not replaced."""
    d = solved_copy(base, tmp)
    os.mkfifo(tmp / "r.html")
    return Spec(["report", str(d), "-o", str(tmp / "r.html")], 2, ("r.html", "regular file"))


@case("touched")
def apply_output_a_fifo(base, tmp):
    os.mkfifo(tmp / "o.csv")
    argv, _ = _apply_argv(base, tmp, tmp / "o.csv")
    return Spec(argv, 2, ("o.csv", "regular file"))


@case("report_o")
def report_o_ok_elsewhere(base, tmp):
    return Spec(["report", str(base / "rows_solved"), "-o", str(tmp / "r" / "x.html")], 0, output=tmp / "r")


@case("report_o")
def report_of_noise_output(base, tmp):
    res = run_cli(["noise", str(base / "static" / "problem.yaml"), "-o", str(tmp / "n"), "-q"])
    if res["rc"] != 0:  # the noise verb itself failed: report on an empty directory instead
        (tmp / "n").mkdir(exist_ok=True)
    return Spec(["report", str(tmp / "n")], 2, ("results.json",))


@case("report_o")
def report_details_of_another_solve(base, tmp):
    """results.json of one solve beside the details.npz of another (20 poses against 12): the report mixed
    them; now refused naming details.npz and the counts."""
    d = solved_copy(base, tmp)
    (d / "results.json").unlink()
    copy(base / "static_solved" / "results.json", d)
    return Spec(["report", str(d)], 2, ("details.npz", "t_start", "12 poses", "found 20"))


@case("report_o")
def report_details_of_another_solve_same_poses(base, tmp):
    """The same number of poses, other residuals: refused by the residual RMS that results.json records."""
    def edit(doc):
        doc["residuals"]["rms"]["imu2"] = [2 * v for v in doc["residuals"]["rms"]["imu2"]]
    return Spec(["report", str(solved_copy(base, tmp, results=edit))], 2, ("details.npz", "residual_acc", "imu2"))


@case("report_o")
def report_of_a_diagnose_directory(base, tmp):
    """diagnose writes results.json, diagnose.json and its own report.html, no details.npz: the error said
    only 'details file not found'."""
    d = tmp / "diag"
    d.mkdir()
    copy(base / "rows_solved" / "results.json", d)
    (d / "diagnose.json").write_text("{}")
    return Spec(["report", str(d)], 2, ("details.npz", "castimate diagnose", "own report.html"))


@case("report_o")
def report_missing_directory(base, tmp):
    return Spec(["report", str(tmp / "nowhere")], 2, ("nowhere",))


def _imutk_apply(base, tmp, gyro, names=(), rc=2, data=None):
    out = tmp / "o.csv"
    return Spec(["apply", str(base / "imutk_solved" / "results.json"), str(data or base / "acc.mat"),
                 "--format", "imutk", "--gyro", str(gyro), "-o", str(out)], rc, names,
                output=out if rc == 0 else None)


@case("apply_gyro")
def apply_gyro_ok(base, tmp):
    out = tmp / "o.csv"

    def check(res):
        rec = read_csv(out)
        if "imu" not in rec.gyro:
            return "no gyroscope in the output"
        return None
    s = _imutk_apply(base, tmp, base / "gyro.mat", rc=0)
    s.check = check
    return s


@case("apply_gyro")
def apply_gyro_missing(base, tmp):
    return _imutk_apply(base, tmp, tmp / "nowhere.mat", ("nowhere.mat",))


@case("apply_gyro")
def apply_gyro_a_directory(base, tmp):
    (tmp / "g.mat").mkdir()
    return _imutk_apply(base, tmp, tmp / "g.mat", ("g.mat", "directory"))


@case("apply_gyro")
def apply_gyro_a_device(base, tmp):
    return _imutk_apply(base, tmp, "/dev/zero", ("/dev/zero", "regular file"))


@case("apply_gyro")
def apply_gyro_garbage(base, tmp):
    (tmp / "g.mat").write_bytes(b"\x00\xff" * 64)
    return _imutk_apply(base, tmp, tmp / "g.mat", ("g.mat",))


@case("apply_gyro")
def apply_gyro_shorter_table(base, tmp):
    """A gyroscope table covering half the session: the accelerometer samples outside it are dropped,
    with a note (interpolating beyond it would invent data)."""
    lines = (base / "gyro.mat").read_text().splitlines()
    (tmp / "g.mat").write_text("\n".join(lines[: len(lines) // 2]) + "\n")
    s = _imutk_apply(base, tmp, tmp / "g.mat", rc=0)
    s.check = lambda res: None if "dropped" in res["stderr"] else "samples dropped without a note"
    return s


@case("apply_gyro")
def apply_gyro_shifted_clock(base, tmp):
    """The gyroscope table's time stamps 100 s later than the accelerometer's: no common samples."""
    rows = [ln.split() for ln in (base / "gyro.mat").read_text().splitlines()]
    (tmp / "g.mat").write_text("\n".join(f"{float(r[0]) + 100:.7e}   " + "   ".join(r[1:]) for r in rows) + "\n")
    return _imutk_apply(base, tmp, tmp / "g.mat", ("g.mat",))


@case("apply_gyro")
def apply_gyro_is_the_output(base, tmp):
    g = copy(base / "gyro.mat", tmp, "g.csv")
    return Spec(["apply", str(base / "imutk_solved" / "results.json"), str(base / "acc.mat"), "--format", "imutk",
                 "--gyro", str(g), "-o", str(g)], 2, ("g.csv", "input"))


@case("apply_gyro")
def apply_gyro_with_csv_data(base, tmp):
    """--gyro belongs to imu_tk's two-file layout; with a csv it would be ignored silently."""
    return Spec(["apply", str(base / "static_solved" / "results.json"), str(base / "static" / "data.csv"),
                 "--gyro", str(base / "gyro.mat"), "-o", str(tmp / "o.csv")], 2, ("--gyro",))


@case("apply_gyro")
def apply_ferraris_results_to_imutk(base, tmp):
    """A one-IMU calibration (imucal table, no recorded units) applied to an imu_tk session of a triad of
    the same name: read with the imutk format's own units, so allowed."""
    out = tmp / "o.csv"
    return Spec(["apply", str(base / "ferraris_solved" / "results.json"), str(base / "acc.mat"), "--format", "imutk",
                 "--gyro", str(base / "gyro.mat"), "-o", str(out)], 0, output=out)


@case("apply_gyro")
def apply_data_in_other_units(base, tmp):
    """A calibration made from SI data applied to the same session in g: refused by the gravity norm."""
    rec = load_rec(base)
    from castimate.io.readers import write_csv
    write_csv(tmp / "g.csv", edited(rec, acc={n: a / G for n, a in rec.acc.items()}))
    return Spec(["apply", str(base / "static_solved" / "results.json"), str(tmp / "g.csv"), "-o", str(tmp / "o.csv")],
                2, ("static_solved", "units.data.accelerometer", "g.csv"))


@case("apply_gyro")
def apply_data_in_mg(base, tmp):
    """The same session in mg (no unit fix to suggest, a factor): the error named the results' units key
    but not the data file whose readings were off; now both."""
    rec = load_rec(base)
    from castimate.io.readers import write_csv
    write_csv(tmp / "mg.csv", edited(rec, acc={n: a * 1000 / G for n, a in rec.acc.items()}))
    return Spec(["apply", str(base / "static_solved" / "results.json"), str(tmp / "mg.csv"), "-o", str(tmp / "o.csv")],
                2, ("static_solved", "units.data.accelerometer", "mg.csv", "factor"))


def _celsius(base, tmp) -> Path:
    """The static session with imu1's temperature logged in °C (25) in a column that must hold kelvin."""
    from castimate.io.readers import write_csv
    rec = load_rec(base)
    return write_csv(tmp / "celsius.csv", edited(rec, temp={"imu1": np.full(len(rec.t), 25.0)})) or tmp / "celsius.csv"


@case("apply_gyro")
def solve_temperature_in_celsius(base, tmp):
    """Temperature effects are fitted relative to the session's mean: a °C column solved as well as kelvin
    and wrote 25 K as the mean, so the calibration later shifted kelvin data by 270 K. Now refused."""
    data = _celsius(base, tmp)
    p = write_yaml(tmp / "problem.yaml", static_problem(data.name, "csv", load_rec(base).triads))
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("celsius.csv", "imu1.temp", "kelvin", "°C"))


@case("apply_gyro")
def apply_temperature_in_celsius(base, tmp):
    """apply refused it inside Calibration.apply, naming 'Calibration.apply: temp['imu1']' instead of the
    file and its column."""
    return Spec(["apply", str(base / "static_solved" / "results.json"), str(_celsius(base, tmp)), "-o",
                 str(tmp / "o.csv")], 2, ("celsius.csv", "imu1.temp", "kelvin", "°C"))


@case("apply_gyro")
def apply_results_of_other_triads(base, tmp):
    return Spec(["apply", str(base / "ferraris_solved" / "results.json"), str(base / "static" / "data.csv"),
                 "-o", str(tmp / "o.csv")], 2, ("data.csv", "imu"))


# ---------------------------------------------------------------- model.intrinsics / model.reuse


def _reuse(base, tmp, intrinsics, names=(), rc=2, reuse=None, which="static"):
    def edit(d):
        d.setdefault("model", {})["intrinsics"] = str(intrinsics)
        if reuse is not None:
            d["model"]["reuse"] = reuse
    p = problem_in(base, tmp, which, edit)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], rc, tuple(names),
                output=tmp / "out" if rc == 0 else None)


def _intrinsics_file(tmp: Path, raw: bytes | str | dict) -> Path:
    p = tmp / "earlier.json"
    p.write_bytes(raw if isinstance(raw, bytes) else (raw if isinstance(raw, str) else json.dumps(raw)).encode())
    return p


@case("reuse")
def reuse_ok_fixed(base, tmp):
    return _reuse(base, tmp, base / "static_solved" / "results.json", rc=0)


@case("reuse")
def reuse_ok_prior(base, tmp):
    return _reuse(base, tmp, base / "static_solved" / "results.json", rc=0, reuse="prior")


@case("reuse")
def reuse_prior_string(base, tmp):
    return _reuse(base, tmp, base / "static_solved" / "results.json", ("problem.yaml", "model.reuse"), reuse="priors")


@case("reuse")
def reuse_prior_bool(base, tmp):
    return _reuse(base, tmp, base / "static_solved" / "results.json", ("problem.yaml", "model.reuse"), reuse=True)


@case("reuse")
def reuse_intrinsics_a_list(base, tmp):
    return _reuse(base, tmp, [1, 2], ("problem.yaml", "model.intrinsics"))


@case("reuse")
def reuse_intrinsics_missing(base, tmp):
    return _reuse(base, tmp, tmp / "nowhere.json", ("problem.yaml", "model.intrinsics", "nowhere.json"))


@case("reuse")
def reuse_intrinsics_directory(base, tmp):
    return _reuse(base, tmp, base / "static_solved", ("problem.yaml", "model.intrinsics", "directory"))


@case("reuse")
def reuse_intrinsics_device(base, tmp):
    return _reuse(base, tmp, "/dev/zero", ("problem.yaml", "model.intrinsics", "regular file"))


@case("reuse")
def reuse_intrinsics_empty(base, tmp):
    return _reuse(base, tmp, _intrinsics_file(tmp, b""), ("earlier.json",))


@case("reuse")
def reuse_intrinsics_truncated(base, tmp):
    raw = (base / "static_solved" / "results.json").read_bytes()
    return _reuse(base, tmp, _intrinsics_file(tmp, raw[: len(raw) // 2]), ("earlier.json",))


@case("reuse")
def reuse_intrinsics_is_a_problem_file(base, tmp):
    return _reuse(base, tmp, base / "static" / "problem.yaml", ("problem.yaml", "JSON"))


@case("reuse")
def reuse_intrinsics_noise_json(base, tmp):
    _intrinsics_file(tmp, {"format": "castimate.noise/1", "triads": {"imu1": {}}})
    return _reuse(base, tmp, tmp / "earlier.json", ("earlier.json", "format"))


@case("reuse")
def reuse_intrinsics_other_triads(base, tmp):
    return _reuse(base, tmp, base / "ferraris_solved" / "results.json", ("problem.yaml", "model.intrinsics", "imu1"))


@case("reuse")
def reuse_intrinsics_not_converged(base, tmp):
    doc = results_doc(base, "static_solved")
    doc["status"]["success"] = False
    return _reuse(base, tmp, _intrinsics_file(tmp, doc), ("earlier.json", "status"))


def _intr_edit(edit):
    def build(base, tmp):
        doc = results_doc(base, "static_solved")
        key = edit(doc)
        return _reuse(base, tmp, _intrinsics_file(tmp, doc), ("earlier.json", key), reuse="prior")
    return build


INTRINSICS_DEFECTS = {
    "gain_strings": lambda d: (d["triads"]["imu2"]["parameters"]["gain"].update(value=["a", "b", "c"]),
                               "triads.imu2.parameters.gain")[1],
    "gain_wrong_size": lambda d: (d["triads"]["imu2"]["parameters"]["gain"].update(value=[1.0, 1.0]),
                                  "triads.imu2.parameters.gain")[1],
    "misalignment_wrong_size": lambda d: (d["triads"]["imu2"]["parameters"]["misalignment"].update(
        value=[0.0] * 5), "triads.imu2.parameters.misalignment")[1],
    "std_negative": lambda d: (d["triads"]["imu2"]["parameters"]["gain"].update(std=[-1e-3] * 3),
                               "triads.imu2.parameters.gain.std")[1],
    "gain_zero": lambda d: (d["triads"]["imu2"]["parameters"]["gain"].update(value=[0.0, 1.0, 1.0]),
                            "triads.imu2.parameters.gain.value")[1],
    "effect_out_of_range": lambda d: (d["triads"]["imu2"]["parameters"].update(
        **{"gyroscope.coupling": {"value": [50.0, 0.0, 0.0]}}), "triads.imu2.parameters.gyroscope.coupling.value")[1],
    "R_nominal_not_rotation": lambda d: (d["triads"]["imu2"].update(R_nominal=[[2, 0, 0], [0, 1, 0], [0, 0, 1]]),
                                         "triads.imu2.R_nominal")[1],
    "parameter_unknown": lambda d: (d["triads"]["imu2"]["parameters"].update(wobble={"value": [1.0]}),
                                    "triads.imu2.parameters.wobble")[1],
}
for _name, _edit in INTRINSICS_DEFECTS.items():
    CASES.append(Case(f"reuse_intrinsics_{_name}", "reuse", _intr_edit(_edit)))


@case("reuse")
def reuse_intrinsics_std_unknown(base, tmp):
    """A σ written as null (undetermined) gives no prior: the group is refitted freely."""
    doc = results_doc(base, "static_solved")
    doc["triads"]["imu2"]["parameters"]["bias"]["std"] = [None, 1e-3, 1e-3]
    return _reuse(base, tmp, _intrinsics_file(tmp, doc), rc=0, reuse="prior")


@case("reuse")
def reuse_dynamic_from_ferraris(base, tmp):
    """A dynamic problem of imu1.. started from a one-IMU Ferraris calibration: names differ."""
    return _reuse(base, tmp, base / "ferraris_solved" / "results.json", ("problem.yaml", "model.intrinsics"),
                  which="dyn")


@case("reuse")
def reuse_static_output_overwrites_intrinsics(base, tmp):
    shutil.copytree(base / "static_solved", tmp / "run")
    p = problem_in(base, tmp, "static", lambda d: d.setdefault("model", {}).update(intrinsics="run/results.json"))
    return Spec(["solve", str(p), "-o", str(tmp / "run"), "-q"], 2, ("results.json", "input"))


# ---------------------------------------------------------------- chip clocks, coupling, elimination


def _dyn_model(edit, names, which="dyn", rc=2):
    def build(base, tmp):
        p = problem_in(base, tmp, which, edit)
        return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], rc, ("problem.yaml",) + tuple(names) if rc else (),
                    output=tmp / "out" if rc == 0 else None)
    return build


def _set(path, value):
    def edit(d):
        x = d
        for k in path[:-1]:
            x = x.setdefault(k, {})
        x[path[-1]] = value
    return edit


EFFECT_KEYS = {
    "clock_beat_in_static": (("model", "accelerometer", "clock_beat"), "free", "model.accelerometer.clock_beat",
                             "static"),
    "clock_drift_in_static": (("model", "accelerometer", "clock_drift"), "free", "model.accelerometer.clock_drift",
                              "static"),
    "coupling_in_static": (("model", "gyroscope", "coupling"), "free", "model.gyroscope.coupling", "static"),
    "clock_beat_string": (("model", "accelerometer", "clock_beat"), "yes", "model.accelerometer.clock_beat", "dyn"),
    "clock_beat_initial_wrong_size": (("model", "accelerometer", "clock_beat"), {"initial": [1e-3, 1e-3]},
                                      "model.accelerometer.clock_beat.initial", "dyn"),
    "clock_beat_initial_huge": (("model", "accelerometer", "clock_beat"), {"initial": 1e300},
                                "model.accelerometer.clock_beat.initial", "dyn"),
    "clock_drift_initial_nan": (("model", "accelerometer", "clock_drift"), {"initial": float("nan")},
                                "model.accelerometer.clock_drift.initial", "dyn"),
    "clock_drift_bounds_inverted": (("model", "accelerometer", "clock_drift"), {"bounds": [1, -1]},
                                    "model.accelerometer.clock_drift.bounds", "dyn"),
    "clock_beat_prior_std_zero": (("model", "accelerometer", "clock_beat"), {"prior": {"mean": 0, "std": 0}},
                                  "model.accelerometer.clock_beat.prior.std", "dyn"),
    "coupling_free_wrong_size": (("model", "gyroscope", "coupling"), {"free": [True, False]},
                                 "model.gyroscope.coupling.free", "dyn"),
    "coupling_initial_huge": (("model", "gyroscope", "coupling"), {"initial": 1e6}, "model.gyroscope.coupling", "dyn"),
    "coupling_per_triad_unknown_triad": (("model", "triads", "imu99", "gyroscope", "coupling"), "free",
                                         "model.triads.imu99", "dyn"),
    "elimination_unknown": (("solver", "elimination"), "schur", "solver.elimination", "dyn"),
    "elimination_bool": (("solver", "elimination"), True, "solver.elimination", "dyn"),
    "elimination_with_bcd": (("solver",), {"elimination": "motion", "method": "bcd", "max_iter": 3},
                             "solver.method", "dyn"),
}
for _name, (_path, _value, _key, _which) in EFFECT_KEYS.items():
    CASES.append(Case(f"effects_{_name}", "effects", _dyn_model(_set(_path, _value), (_key,), _which)))


for _integration, _key, _value in (("euler", "sigma_integration", 1e-300), ("euler", "sigma_s", 1e-300),
                                   ("trapezoid", "sigma_omega_dot", 1e-12), ("euler", "sigma_integration", 1e-8),
                                   ("wiener3", "density_s", 1e-300), ("wiener3", "density_omega", 1e-300),
                                   ("wiener2", "density_omega", 1e-12)):
    CASES.append(Case(f"motion_{_integration}_{_key}_{_value:g}", "effects", _dyn_model(
        _set(("motion",), {"process_model": True, "integration": _integration, "process_noise": "fixed",
                           _key: _value}), (f"motion.{_key}",))))


@case("effects")
def coupling_without_gyroscopes(base, tmp):
    def edit(d):
        for t in d["array"]["triads"]:
            t["gyroscope"] = False
        d["noise"].pop("gyroscope", None)  # unused with every gyroscope off: refused on its own
        d.setdefault("model", {})["gyroscope"] = {"coupling": "free"}
    return _dyn_model(edit, ("model.gyroscope.coupling", "no gyroscope"))(base, tmp)


@case("effects")
def clock_beat_ok(base, tmp):
    def edit(d):
        d.setdefault("model", {}).setdefault("accelerometer", {})["clock_beat"] = "free"
        d["motion"] = {"process_model": False}
    return _dyn_model(edit, (), rc=0)(base, tmp)


@case("effects")
def clock_beat_ok_with_process_model(base, tmp):
    return _dyn_model(_set(("model", "accelerometer", "clock_beat"), "free"), (), rc=0)(base, tmp)


@case("effects")
def clock_beat_irregular_time(base, tmp):
    """The chip-clock effects need the sample rate: time stamps with a 5 s gap are refused by name."""
    rec = read_csv(base / "dyn" / "data.csv")
    t = rec.t.copy()
    t[100:] += 5.0
    doc = problem_doc(base, "dyn")
    doc.setdefault("model", {}).setdefault("accelerometer", {})["clock_beat"] = "free"
    p = with_data(base, tmp, edited(rec, t=t), problem=doc)
    return Spec(["solve", str(p), "-o", str(tmp / "out"), "-q"], 2, ("data.csv", "gap", "clock_beat"))


@case("effects")
def elimination_none_ok(base, tmp):
    def edit(d):
        d["solver"] = {"elimination": "none"}
        d["motion"] = {"process_noise": "fixed"}
    return _dyn_model(edit, (), rc=0)(base, tmp)


@case("effects")
def elimination_none_ok_process_noise_auto(base, tmp):
    """The full NLP's refit at the estimated process-noise levels ends at the optimum with IPOPT's
    dual infeasibility at a round-off floor above its tolerance (max_iter): converged by the
    Newton decrement (Solver.solve). Seven full-NLP solves, 12 s of CPU: a longer wall-time limit
    on a shared machine."""
    return replace(_dyn_model(_set(("solver", "elimination"), "none"), (), rc=0)(base, tmp), timeout=300)


# ---------------------------------------------------------------- batch, montecarlo, plan (refused before any cluster starts)


def _plan_file(tmp: Path, plan: str, extra: str = "") -> Path:
    p = tmp / "plan.yaml"
    p.write_text(f"kind: static_array\ntriads: 3\nposes: 12\n{extra}plan: {plan}\n")
    return p


SCALE_CASES = {
    "batch_recording_is_a_device": (lambda b, t: ["batch", str(b / "static" / "problem.yaml"), "/dev/zero", "-o",
                                                  str(t / "o"), "--workers", "1"], ("/dev/zero", "regular file")),
    "batch_recording_is_a_directory": (lambda b, t: ["batch", str(b / "static" / "problem.yaml"), str(b / "static"),
                                                     "-o", str(t / "o"), "--workers", "1"], ("static", "directory")),
    "batch_glob_matches_nothing": (lambda b, t: ["batch", str(b / "static" / "problem.yaml"), str(t / "x*.csv"), "-o",
                                                 str(t / "o"), "--workers", "1"], ("x*.csv", "glob")),
    "batch_template_is_a_scenario": (lambda b, t: ["batch", str(b / "rows.yaml"), str(b / "static" / "data.csv"),
                                                   "-o", str(t / "o"), "--workers", "1"], ("rows.yaml", "data")),
    "batch_template_ferraris": (lambda b, t: ["batch", str(b / "ferraris" / "problem.yaml"),
                                              str(b / "ferraris" / "session.csv"), "-o", str(t / "o"), "--workers",
                                              "1"], ("problem.yaml", "sections")),
    "batch_workers_zero": (lambda b, t: ["batch", str(b / "static" / "problem.yaml"), str(b / "static" / "data.csv"),
                                         "-o", str(t / "o"), "--workers", "0"], ("--workers",)),
    "batch_threshold_nan": (lambda b, t: ["batch", str(b / "static" / "problem.yaml"), str(b / "static" / "data.csv"),
                                          "-o", str(t / "o"), "--workers", "1", "--outlier-threshold", "nan"],
                            ("--outlier-threshold",)),
    "batch_scheduler_not_an_address": (lambda b, t: ["batch", str(b / "static" / "problem.yaml"),
                                                     str(b / "static" / "data.csv"), "-o", str(t / "o"), "--scheduler",
                                                     "nonsense"], ("--scheduler",)),
    "batch_output_is_a_file": (lambda b, t: ["batch", str(b / "static" / "problem.yaml"), str(b / "static" / "data.csv"),
                                             "-o", str(b / "static" / "data.csv"), "--workers", "1"],
                               ("data.csv", "directory")),
    "montecarlo_one_run": (lambda b, t: ["montecarlo", str(b / "rows.yaml"), "--runs", "1", "-o", str(t / "o")],
                           ("--runs",)),
    "montecarlo_runs_unbounded": (lambda b, t: ["montecarlo", str(b / "rows.yaml"), "--runs", "100000000", "-o",
                                                str(t / "o")], ("--runs",)),
    "montecarlo_problem_file": (lambda b, t: ["montecarlo", str(b / "static" / "problem.yaml"), "--runs", "2", "-o",
                                              str(t / "o"), "--workers", "1"], ("problem.yaml", "problem file")),
    "montecarlo_scenario_a_device": (lambda b, t: ["montecarlo", "/dev/zero", "--runs", "2", "-o", str(t / "o")],
                                     ("/dev/zero", "regular file")),
    "plan_problem_file": (lambda b, t: ["plan", str(b / "static" / "problem.yaml"), "-o", str(t / "o")],
                          ("problem.yaml", "problem file")),
    "plan_no_plan_key": (lambda b, t: ["plan", str(b / "rows.yaml"), "-o", str(t / "o")], ("rows.yaml", "plan")),
    "plan_durations_empty": (lambda b, t: ["plan", str(_plan_file(t, "{durations: []}")), "-o", str(t / "o")],
                             ("plan.yaml", "plan.durations")),
    "plan_duration_negative": (lambda b, t: ["plan", str(_plan_file(t, "{durations: [-1, 5]}")), "-o", str(t / "o")],
                               ("plan.yaml", "plan.durations[0]")),
    "plan_duration_unbounded": (lambda b, t: ["plan", str(_plan_file(t, "{durations: [1.0e+12]}")), "-o",
                                              str(t / "o")], ("plan.yaml", "plan.durations[0]")),
    "plan_durations_a_string": (lambda b, t: ["plan", str(_plan_file(t, "{durations: soon}")), "-o", str(t / "o")],
                                ("plan.yaml", "plan.durations")),
    "plan_unknown_key": (lambda b, t: ["plan", str(_plan_file(t, "{durations: [10], extra: 1}")), "-o", str(t / "o")],
                         ("plan.yaml", "plan.extra")),
    "plan_time_series": (lambda b, t: ["plan", str(_plan_file(t, "{durations: [10]}", "time_series: true\n")), "-o",
                                       str(t / "o")], ("plan.yaml", "time_series")),
    "plan_output_overwrites_plan": (lambda b, t: ["plan", str(_plan_file(t, "{durations: [10]}").rename(
        t / "plan.json") or t / "plan.json"), "-o", str(t)], ("plan.json", "input")),
}
for _name, (_argv, _names) in SCALE_CASES.items():
    def _scale_case(base, tmp, _argv=_argv, _names=_names):
        return Spec(_argv(base, tmp), 2, _names)
    CASES.append(Case(_name, "scale", _scale_case))


# ============================================================================ the test


@pytest.mark.parametrize("c", [pytest.param(c, id=c.id, marks=c.marks) for c in CASES])
def test_adversarial(c: Case, base: Path, tmp_path: Path):
    spec = c.build(base, tmp_path)
    before = snapshot(tmp_path, base)
    res = run_cli(spec.argv, timeout=spec.timeout)
    after = snapshot(tmp_path, base)
    kind, why = outcome(spec, res, before, after, tmp_path)
    assert kind == "clean", f"{kind}: {why}"


# ============================================================================ the table


def tabulate(base: Path, work: Path, only: str | None = None) -> list[tuple[Case, str, str]]:
    rows = []
    for c in CASES:
        if only and not any(o == c.klass or o in c.id for o in only.split(",")):
            continue
        tmp = work / c.id
        tmp.mkdir()
        try:
            spec = c.build(base, tmp)
        except Exception:  # noqa: BLE001
            rows.append((c, "build error", traceback.format_exc().splitlines()[-1]))
            continue
        before = snapshot(tmp, base)
        res = run_cli(spec.argv)
        after = snapshot(tmp, base)
        kind, why = outcome(spec, res, before, after, tmp)
        rows.append((c, kind, why))
        print(f"{kind:14s} {c.klass:10s} {c.id}: {why[:300]}", flush=True)
    return rows


if __name__ == "__main__":
    import tempfile

    root = Path(tempfile.mkdtemp(prefix="adv"))
    (root / "base").mkdir()
    (root / "cases").mkdir()
    b = build_base(root / "base")
    rows = tabulate(b, root / "cases", sys.argv[1] if len(sys.argv) > 1 else None)
    table = Counter((c.klass, k) for c, k, _ in rows)
    print("\n| class | " + " | ".join(OUTCOMES) + " | total |")
    print("|---|" + "---|" * (len(OUTCOMES) + 1))
    for kl in sorted({c.klass for c, _, _ in rows}):
        n = sum(v for (k2, _), v in table.items() if k2 == kl)
        print(f"| {kl} | " + " | ".join(str(table[kl, o]) for o in OUTCOMES) + f" | {n} |")
    tot = Counter(k for _, k, _ in rows)
    print("| all | " + " | ".join(str(tot[o]) for o in OUTCOMES) + f" | {len(rows)} |")
    shutil.rmtree(root, ignore_errors=True)

"""The one validation style for user-facing input: small checks that raise a one-line
:class:`~castimate.errors.InputError` naming the file, the key path, what was expected and what
was found. Problem files, scenario files, detection options, unit declarations and results files use it.

It also guards the edges where input enters: :func:`read_input_bytes` / :func:`read_input_text`
read only regular files (not a directory, a device or a FIFO) of a bounded size, in UTF-8, and
:func:`load_yaml` reads YAML bounded in size, depth and integer length, refusing duplicate keys.
"""

from __future__ import annotations

import json
import os
import re
import stat
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .errors import InputError


def shown(v: Any) -> str:
    """``repr(v)`` for a message, shortened: huge integers by their size, long values cut."""
    if isinstance(v, int) and not isinstance(v, bool) and v.bit_length() > 100:
        return f"an integer of about {int(v.bit_length() * 0.30103) + 1} digits"
    try:
        r = repr(v)
    except ValueError:  # an int too large to print
        return f"a {type(v).__name__} too large to print"
    return r if len(r) <= 80 else r[:77] + "..."


def range_text(lo, hi, unit: str) -> str:
    """'from lo to hi unit', 'at least lo unit' or 'at most hi unit'."""
    u = f" {unit}" if unit else ""
    if lo is not None and hi is not None:
        return f"from {lo:g} to {hi:g}{u}"
    return f"at least {lo:g}{u}" if lo is not None else f"at most {hi:g}{u}"


def within_range(source: object, where: str, values, lo, hi, components, unit: str) -> np.ndarray:
    """``values`` (one per component) inside [lo, hi] each, else a one-line InputError naming the first
    component outside: "expected <component> from lo to hi <unit> (the physical range), found v"."""
    v = np.asarray(values, float)
    bad = ~((v >= lo) & (v <= hi))  # NaN is outside too
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(source, where, f"expected {components[i]} {range_text(lo[i], hi[i], '' if unit == '-' else unit)} "
                                        f"(the physical range), found {v[i]:g}")
    return v


class Check:
    """Small validators that raise one-line InputErrors naming the file and key path."""

    def __init__(self, source: Path):
        self.source = source

    def fail(self, where: str, msg: str):
        raise InputError(self.source, where, msg)

    def mapping(self, v, where, allowed, required=()):
        if v is None:
            v = {}
        if not isinstance(v, dict):
            self.fail(where, f"expected a mapping, found {type(v).__name__} {v!r}")
        for k in v:
            if allowed is not None and k not in allowed:
                self.fail(f"{where}.{k}" if where else str(k),
                          f"unknown key; expected one of {', '.join(sorted(map(str, allowed)))}")
        for k in required:
            if k not in v:
                self.fail(where or "(top level)", f"missing required key {k!r}")
        return v

    def number(self, v, where, positive=False, integer=False, lo=None, hi=None, unit=""):
        """A finite number (``integer``: a whole one), optionally positive and within [lo, hi] in ``unit``,
        the physical range of the key, named with it in the message."""
        ok = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
        try:
            x = float(v) if ok else None
        except OverflowError:  # an integer beyond any float
            x = None
        if x is None or not np.isfinite(x) or (positive and x <= 0) or (integer and int(v) != v):
            kind = "a positive " if positive else "an " if integer else "a "
            kind += "integer" if integer else "finite number"
            self.fail(where, f"expected {kind}, found {shown(v)}")
        if (lo is not None and x < lo) or (hi is not None and x > hi):
            self.fail(where, f"expected {'an integer' if integer else 'a number'} {range_text(lo, hi, unit)}, "
                             f"found {shown(v)}")
        return int(v) if integer else x

    def flag(self, v, where):
        if not isinstance(v, bool):
            self.fail(where, f"expected true or false, found {shown(v)}")
        return v

    def choice(self, v, where, options):
        if v not in options:
            self.fail(where, f"expected one of {', '.join(options)}, found {shown(v)}")
        return v

    def vector(self, v, where, n, kind=float, **bounds):
        """A scalar (broadcast) or a list of exactly n values (``bounds``: as for :meth:`number`)."""
        items = v if isinstance(v, list) else [v] * n
        if len(items) != n:
            self.fail(where, f"expected a scalar or a list of {n} values, found a list of {len(items)}")
        out = []
        for i, x in enumerate(items):
            w = f"{where}[{i}]" if isinstance(v, list) else where
            if kind is bool:
                if not isinstance(x, bool):
                    self.fail(w, f"expected true or false, found {x!r}")
                out.append(x)
            else:
                out.append(self.number(x, w, **bounds))
        return tuple(out)

    def matrix3(self, v, where):
        a = np.asarray(v, dtype=object)
        if a.shape != (3, 3):
            self.fail(where, f"expected a 3x3 matrix (list of 3 rows), found shape {a.shape}")
        m = np.array([[self.number(a[i, j], f"{where}[{i}][{j}]") for j in range(3)] for i in range(3)])
        if not np.allclose(m @ m.T, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
            self.fail(where, "expected a proper rotation matrix (orthonormal, det +1)")
        return m


# ---------------------------------------------------------------------------------------------
# Files at the edge: type, size, encoding, bounded YAML
# ---------------------------------------------------------------------------------------------

#: Largest problem, scenario or results file read, bytes (they are a few kB).
MAX_TEXT_BYTES = 1 << 20
#: Deepest nesting of mappings and lists in a YAML file (a problem file needs 6).
MAX_YAML_DEPTH = 32
#: Most YAML values after expanding aliases (a problem file has a few hundred).
MAX_YAML_NODES = 200_000
#: Integers with more digits are refused where YAML is read, before they overflow a float.
MAX_INT_DIGITS = 30


def as_path(v: Any, function: str, argument: str, expected: str = "a path") -> Path:
    """An API argument as a Path; a value that is not a path is a TypeError naming the argument, an
    empty string an InputError (``Path("")`` is the current directory: ``castimate.write(outcome, "")``
    wrote results.json there)."""
    if not isinstance(v, (str, os.PathLike)):
        raise TypeError(f"{function}: {argument}: expected {expected}, found {type(v).__name__} {shown(v)}")
    if isinstance(v, str) and not v:
        raise InputError(function, argument, f"expected {expected}, found an empty string")
    return Path(v)


def plain_values(v: Any, source: object, where: str = "", depth: int = 1) -> Any:
    """A problem given as a Python dict, with the values a YAML file holds: numpy arrays as (nested)
    lists, numpy scalars as Python ones, tuples as lists. The checks compare values with names
    (``v == "auto"``, ``v in ("free", "fixed")``), which an array answers element by element:
    ``noise: {accelerometer: np.array([...])}`` raised numpy's "truth value of an array is
    ambiguous". Nested at most :data:`MAX_YAML_DEPTH` deep, as a YAML file (a dict holding itself is
    refused by that too)."""
    if depth > MAX_YAML_DEPTH:
        raise InputError(source, where, f"expected mappings and lists nested at most {MAX_YAML_DEPTH} deep, "
                                        "found deeper nesting")
    if isinstance(v, dict):
        return {k: plain_values(x, source, f"{where}.{k}" if where else str(k), depth + 1) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain_values(x, source, f"{where}[{i}]", depth + 1) for i, x in enumerate(v)]
    if isinstance(v, (np.ndarray, np.generic)):
        return plain_values(v.tolist(), source, where, depth)
    return v


def input_file(path: str | os.PathLike, what: str = "file", source: object = None, where: str = "") -> os.stat_result:
    """Check that ``path`` is an existing regular file (not a directory, device or FIFO); return its stat.

    The error names ``source`` and ``where`` (the file and key that gave the path) when given, else the path.
    """
    p = Path(path)
    named = source is not None
    subject = f"{what} {p}" if named else what

    def fail(msg: str):
        raise InputError(source if named else p, where, msg)

    try:
        st = os.stat(p)
    except FileNotFoundError:
        fail(f"{subject} does not exist" if named else f"{what} not found")
    except NotADirectoryError:
        fail(f"{subject} does not exist (a part of its path is a file)")
    except OSError as e:
        fail(f"cannot read {subject} ({e.strerror})")
    if stat.S_ISDIR(st.st_mode):
        fail(f"cannot read {subject}: it is a directory; expected a file")
    if not stat.S_ISREG(st.st_mode):
        fail(f"cannot read {subject}: it is not a regular file (a device, FIFO or socket); expected a file")
    return st


def read_input_bytes(path: str | os.PathLike, what: str = "file", max_bytes: int | None = None) -> bytes:
    """The bytes of a regular file, refused if it is a directory, a device or larger than ``max_bytes``."""
    st = input_file(path, what)
    if max_bytes is not None and st.st_size > max_bytes:
        raise InputError(path, "", f"expected a {what} of at most {max_bytes / 2 ** 20:g} MB, found "
                                   f"{st.st_size / 2 ** 20:.1f} MB")
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except OSError as e:
        raise InputError(path, "", f"cannot read ({e.strerror})") from None


def decode_utf8(raw: bytes, path: object, what: str = "file") -> str:
    """UTF-8 text (a leading byte-order mark dropped); a non-UTF-8 byte is named with its line."""
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise InputError(path, f"line {line}", f"expected UTF-8 text in the {what}, found the byte 0x{raw[e.start]:02x}; "
                                               "save the file as UTF-8") from None


def read_input_text(path: str | os.PathLike, what: str = "file", max_bytes: int | None = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of a regular file of at most ``max_bytes``."""
    return decode_utf8(read_input_bytes(path, what, max_bytes), path, what)


def _line(mark) -> str:
    return f"line {mark.line + 1}" if mark is not None else ""


def _check_nodes(node: yaml.Node, path: object, where: str, sizes: dict[int, int]) -> int:
    """Refuse duplicate mapping keys, integers too long to be a quantity and aliases inside the value
    they name (a cycle), naming the key path; return the node count with aliases expanded."""
    if id(node) in sizes:
        if sizes[id(node)] < 0:  # still being counted: an alias inside the value it names
            raise InputError(path, where, f"expected values without cycles, found an alias to a value that contains "
                                          f"it ({_line(node.start_mark)})")
        return sizes[id(node)]
    sizes[id(node)] = -1
    n = 1
    if isinstance(node, yaml.MappingNode):
        seen: dict[Any, yaml.Node] = {}
        for k, v in node.value:
            key = k.value if isinstance(k, yaml.ScalarNode) else None
            kw = f"{where}.{key}" if where else str(key)
            if key is not None and key != "<<":
                if key in seen:
                    raise InputError(path, kw, f"duplicate key ({_line(seen[key].start_mark)} and "
                                               f"{_line(k.start_mark)}); YAML would silently keep the second")
                seen[key] = k
            n += _check_nodes(k, path, kw, sizes) + _check_nodes(v, path, kw, sizes)
    elif isinstance(node, yaml.ScalarNode) and node.tag == "tag:yaml.org,2002:int":
        digits = sum(ch.isdigit() for ch in node.value)
        if digits > MAX_INT_DIGITS:
            raise InputError(path, where, f"expected a number, found an integer of {digits} digits ({_line(node.start_mark)})")
    elif isinstance(node, yaml.SequenceNode):
        for i, v in enumerate(node.value):
            n += _check_nodes(v, path, f"{where}[{i}]", sizes)
    sizes[id(node)] = n
    if n > MAX_YAML_NODES:
        raise InputError(path, where, f"expected at most {MAX_YAML_NODES} YAML values (aliases expanded), found more")
    return n


class YamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader, with YAML 1.2's floats without a dot (``1e-3``, ``2E+6``): YAML 1.1 reads
    them as text, and ``tol: 1e-10`` was refused as "found '1e-10'"."""


YamlLoader.add_implicit_resolver("tag:yaml.org,2002:float",
                                 re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"), list("-+0123456789"))


def load_yaml(path: str | os.PathLike, what: str = "problem file") -> Any:
    """A YAML file read at the edge: a regular UTF-8 file of at most 1 MB, nested at most 32 deep,
    without duplicate keys or integers longer than 30 digits (the key path named), before Python
    objects are built from it."""
    text = read_input_text(path, what)
    try:
        depth = 0
        for ev in yaml.parse(text, Loader=yaml.SafeLoader):  # event by event: no recursion
            if isinstance(ev, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_YAML_DEPTH:
                    raise InputError(path, _line(ev.start_mark), f"expected mappings and lists nested at most "
                                                                 f"{MAX_YAML_DEPTH} deep, found deeper nesting")
            elif isinstance(ev, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
        loader = YamlLoader(text)
        try:
            node = loader.get_single_node()
            if node is None:
                return None
            _check_nodes(node, path, "", {})
            return loader.construct_document(node)
        finally:
            loader.dispose()
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        raise InputError(path, _line(mark), f"not valid YAML ({getattr(e, 'problem', None) or e})") from None


class _Rejected(Exception):
    """JSON text holds a key twice in one object or an integer longer than MAX_INT_DIGITS (the first pass
    of :func:`parse_json`; the second names it)."""


def _json_int(digits: str) -> int:
    if len(digits.lstrip("-")) > MAX_INT_DIGITS:
        raise _Rejected
    return int(digits)


def _unique(pairs: list) -> dict:
    d = dict(pairs)
    if len(d) != len(pairs):
        raise _Rejected
    return d


class _Pairs(list):
    """A JSON object's (key, value) pairs in file order (the second pass of :func:`parse_json`)."""


class _Digits(str):
    """The digits of an integer longer than MAX_INT_DIGITS (the second pass of :func:`parse_json`)."""


def _name_rejected(v: Any, path: object, where: str = "") -> None:
    """Refuse the first key given twice in one object, or integer longer than MAX_INT_DIGITS, of JSON parsed
    with its objects as _Pairs and those integers as _Digits, naming its key path."""
    if isinstance(v, _Digits):
        raise InputError(path, where, f"expected a number, found an integer of {len(v.lstrip('-'))} digits")
    if isinstance(v, _Pairs):
        seen = set()
        for k, x in v:
            w = f"{where}.{k}" if where else k
            if k in seen:
                raise InputError(path, w, "duplicate key; JSON readers differ in which value they keep")
            seen.add(k)
            _name_rejected(x, path, w)
    elif isinstance(v, list):
        for i, x in enumerate(v):
            _name_rejected(x, path, f"{where}[{i}]")


def parse_json(text: str, path: object) -> Any:
    """JSON text (of a results file, a section list) parsed; invalid JSON and nesting too deep for the parser
    are refused with the line, a key given twice in one object and an integer longer than MAX_INT_DIGITS with
    the key path, as :func:`load_yaml` refuses them in YAML. json.loads kept the second of two keys silently,
    and a longer integer became an internal error later: OverflowError where it was read as a float,
    ValueError beyond Python's 4300 digits."""
    try:
        try:
            return json.loads(text, parse_int=_json_int, object_pairs_hook=_unique)
        except _Rejected:  # parsed again, to name it
            _name_rejected(json.loads(text, object_pairs_hook=_Pairs, parse_int=lambda s: _Digits(s) if len(
                s.lstrip("-")) > MAX_INT_DIGITS else int(s)), path)
            raise
    except RecursionError:
        raise InputError(path, "", "not valid JSON (nested too deeply)") from None
    except json.JSONDecodeError as e:
        raise InputError(path, f"line {e.lineno}", f"not valid JSON ({e.msg})") from None

"""Atomic output: readers never see a half-written file, and a failed write leaves any old file intact."""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import signal
import stat
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Callable

from ..errors import InputError


def atomic_write(path: str | os.PathLike, write: Callable[[IO[bytes]], None]) -> None:
    """Write ``path`` through a temporary file in the same directory and ``os.replace``.

    Readers never see a half-written file, and a failed write leaves any old file intact.
    """
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    try:
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{target.name}.", suffix=".tmp")
    except OSError as exc:
        raise InputError(target, "", f"cannot write to directory {str(directory)!r}: {exc.strerror}") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp creates mode 0600; keep an existing file's mode, else the usual 0644.
        try:
            mode = stat.S_IMODE(os.stat(target).st_mode)
        except FileNotFoundError:
            mode = 0o644
        os.chmod(tmp, mode)
        try:
            os.replace(tmp, target)
        except OSError as exc:
            raise InputError(target, "", f"cannot write ({exc.strerror})") from None
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def write_atomic(path: str | os.PathLike, data: bytes | str) -> None:
    """Write bytes or text (UTF-8) to ``path`` atomically, creating its directory."""
    check_output(path, directory=False)
    try:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(path, "", f"cannot create the directory {Path(path).parent} ({e.strerror})") from None
    raw = data.encode() if isinstance(data, str) else data
    atomic_write(path, lambda fh: fh.write(raw))


# ---------------------------------------------------------------------------------------------
# Outputs staged and moved into place only on success
# ---------------------------------------------------------------------------------------------

def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def _existing_ancestor(path: Path) -> Path:
    p = Path(os.path.abspath(path))
    while not os.path.lexists(p):
        p = p.parent
    return p


def check_output(target: str | os.PathLike, directory: bool, names: tuple[str, ...] = (),
                 inputs: tuple = (), option: str = "-o") -> None:
    """Refuse, before any work, an output that cannot be written or would replace an input.

    ``target`` is an output directory (``directory``) holding ``names``, or an output file. Refused:
    a file where the directory goes, a directory where a file goes, a path under a file or where
    nothing can be created, and any output file that is one of ``inputs`` (same file, however spelt).
    """
    target = Path(target)
    if directory and target.exists() and not target.is_dir():
        raise InputError(target, option, "expected an output directory, found a file")
    if not directory and target.is_dir():
        raise InputError(target, option, "is a directory; expected an output file")
    anchor = _existing_ancestor(target if directory else target.parent)
    if not anchor.is_dir():
        raise InputError(target, option, f"cannot be created: {anchor} is a file, not a directory")
    if not os.access(anchor, os.W_OK | os.X_OK):
        raise InputError(target, option, f"cannot be created: no permission to write in {anchor}")
    slots = [target / n for n in names] if directory else [target]
    for slot in slots:
        if slot.is_dir():
            raise InputError(slot, option, "is a directory; expected a file to write (remove or rename it)")
        if os.path.lexists(slot) and not (slot.is_symlink() or stat.S_ISREG(os.stat(slot).st_mode)):
            raise InputError(slot, option, "is not a regular file (a device, FIFO or socket); refusing to replace it: "
                                           "choose another output")
        for inp in inputs:
            if inp is not None and os.path.lexists(slot) and _same_file(slot, Path(inp)):
                raise InputError(slot, option, f"is an input of this command ({inp}); refusing to overwrite an input: "
                                               "choose another output")


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold back Ctrl-C (SIGINT) until the block is done, then act on it as before (KeyboardInterrupt
    by default): for a few renames that must happen all together. Outside the main thread signals
    cannot be handled, and the block runs as it is."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous is None:  # None: set outside Python
        yield
        return
    caught: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught and previous in (signal.default_int_handler, signal.SIG_DFL):
        raise KeyboardInterrupt
    if caught and callable(previous):
        previous(signal.SIGINT, None)


class StagedOutput:
    """Write a command's outputs into a hidden staging directory; move them into place only on success.

    ``with StagedOutput(target, directory=True, names=..., inputs=...) as stage:`` checks the target
    first (:func:`check_output`), yields the staging directory (or, for a file target, the staged
    file's path), and on a normal exit moves every staged file to the target (each an atomic rename,
    after all are checked). On an exception nothing is moved and the stage is removed: a failed
    command leaves no partial output. A move that fails (a disk error between two renames) undoes
    the others and puts the previous outputs back (:class:`_Publication`). ``stale``: files of the
    target directory that describe its previous outputs (``castimate report``'s report.html beside
    results.json; a batch's per-recording files), removed together with the moves unless this run
    writes them anew, so that none is left beside new outputs it does not describe.
    """

    def __init__(self, target: str | os.PathLike, directory: bool = True, names: tuple[str, ...] = (),
                 inputs: tuple = (), option: str = "-o", stale: tuple[str, ...] = ()):
        self.target, self.directory, self.inputs, self.option = Path(target), directory, tuple(inputs), option
        self.stale = stale
        check_output(self.target, directory, names, self.inputs, option)
        self.stage: Path | None = None

    def __enter__(self) -> Path:
        anchor = _existing_ancestor(self.target if self.directory else self.target.parent)
        try:
            self.stage = Path(tempfile.mkdtemp(prefix=".castimate-stage-", dir=anchor))
        except OSError as e:
            raise InputError(self.target, self.option, f"cannot write in {anchor} ({e.strerror})") from None
        return self.stage if self.directory else self.stage / self.target.name

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                self._commit()
        finally:
            if self.stage is not None:
                shutil.rmtree(self.stage, ignore_errors=True)

    def _commit(self) -> None:
        staged = sorted(p for p in self.stage.rglob("*") if p.is_file())
        moves = [(p, (self.target / p.relative_to(self.stage)) if self.directory else self.target) for p in staged]
        check_output(self.target, self.directory, tuple(str(d.relative_to(self.target)) for _, d in moves)
                     if self.directory else (), self.inputs, self.option)
        placed = {dest for _, dest in moves}
        stale = [self.target / name for name in self.stale
                 if os.path.lexists(self.target / name) and self.target / name not in placed]
        publication = _Publication(self.stage)
        try:
            with interrupts_deferred():  # a Ctrl-C between two renames would pair new and old files
                for _, dest in moves:
                    publication.make_parents(dest)
                for i, (_, dest) in enumerate(moves):  # the previous outputs kept until all are in place
                    publication.keep(dest, f"{i}")
                for i, path in enumerate(stale):
                    publication.keep(path, f"stale{i}")
                for src, dest in moves:
                    publication.replace(src, dest)
                for path in stale:
                    publication.remove(path)
        except OSError as e:
            failed = publication.roll_back()
            what = ("; the previous outputs are in place again" if not failed else
                    f"; could not restore {', '.join(map(str, failed))} (the previous versions are kept in "
                    f"{publication.backup}, which is left in place)")
            if failed:
                self.stage = None  # keep the stage: it holds the previous outputs
            raise InputError(self.target, self.option, f"cannot write the output ({e.strerror or e}){what}") from None


class _Publication:
    """The moves of a set of staged outputs into place, undone together if one of them fails.

    Before any move, every file about to be replaced or removed is hard-linked (or copied, where the
    file system has no hard links) into ``backup``, a directory in the stage (so on the outputs' file
    system, and removed with it on success); :meth:`roll_back` puts those back by rename and
    removes the new files and the directories created, so that a disk error (ENOSPC, EIO) between two
    renames leaves the previous set of outputs, not a mix. POSIX renames a single file atomically, not
    several: a reader may see the new files for the moment before the roll back."""

    def __init__(self, stage: Path):
        self.stage = stage
        self.kept: dict[Path, Path] = {}  # destination -> its previous version
        self.done: list[tuple[str, Path]] = []  # ("mkdir" | "placed" | "removed", path), in order

    @functools.cached_property
    def backup(self) -> Path:
        return Path(tempfile.mkdtemp(prefix=".previous-", dir=self.stage))

    def make_parents(self, dest: Path) -> None:
        missing = [p for p in (dest.parent, *dest.parent.parents) if not os.path.lexists(p)]
        for p in reversed(missing):
            p.mkdir()
            self.done.append(("mkdir", p))

    def keep(self, dest: Path, name: str) -> None:
        if not os.path.lexists(dest) or dest in self.kept:
            return
        copy = self.backup / name
        if dest.is_symlink():
            os.symlink(os.readlink(dest), copy)
        else:
            try:
                os.link(dest, copy)
            except OSError:
                shutil.copy2(dest, copy)
        self.kept[dest] = copy

    def replace(self, src: Path, dest: Path) -> None:
        os.replace(src, dest)
        self.done.append(("placed", dest))

    def remove(self, path: Path) -> None:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
            self.done.append(("removed", path))

    def roll_back(self) -> list[Path]:
        """Undo the moves, newest first; the paths that could not be restored."""
        failed = []
        for what, path in reversed(self.done):
            try:
                if what == "mkdir":
                    path.rmdir()
                elif path in self.kept:
                    os.replace(self.kept[path], path)
                elif what == "placed":
                    path.unlink()
            except OSError:
                failed.append(path)
        return failed

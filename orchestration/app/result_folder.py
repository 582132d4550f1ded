"""The result folder of a command-line run: checked and locked before the run, replaced at its end.

A run never writes into the folder that holds earlier results. It writes into a sibling
``<out>.running`` and, when it ends, moves that folder into place:

* a run that **completed** (or was terminated by an FMU, which is a normal end) replaces ``<out>``
  (an atomic exchange of the two folders where the kernel offers it, then the old one is removed);
* a run that was **interrupted** (Ctrl-C, SIGTERM) or **failed** becomes ``<out>.interrupted`` or
  ``<out>.failed`` (replacing an earlier folder of that name), and ``<out>`` keeps the last
  complete run. Why beside and not in place: the partial rows are results and are kept, but a
  user who presses Ctrl-C expects the earlier complete results to survive, and repeated
  interruptions must never eat them either; the summary and the message name the folder.
* a run that was **killed** (SIGKILL, power loss) leaves ``<out>.running``; the next run into the
  same ``--out`` renames it ``<out>.killed`` (with a note) before it starts.

``<out>.lock`` holds the PID of the run using ``<out>`` (an ``fcntl.flock`` on it, which the
kernel drops when that process dies): a second run into the same ``--out`` is refused naming the
folder and that PID; a lock left by a dead process is taken over with a note.

**A run deletes only what runs wrote.** ``<out>`` is replaced as a whole, so a folder that holds
anything a run did not write (``my_notes.txt``, ``analysis/``) is *refused* before anything runs,
naming what it holds and the fix (move those out, or choose another ``--out``); a folder holding
only the results of an earlier run is replaced as before. Why refuse rather than carry the user's
files over into the new folder: publishing is one atomic exchange of two folders, which a kill at
any moment leaves either old or new; carrying files over would be a series of moves between two
folders that a kill or a full disk could stop half-way, and the files would then sit in a
``<out>.running`` that the next run files away as ``<out>.killed``. Refusing keeps the one
exchange and is safe by construction. What a run wrote is recognised file by file
(:func:`foreign_entries`): ``summary.json`` and ``units.json`` as the run writes them, the files
the earlier run's ``summary.json`` lists (its CSVs, ``.pvd`` files and plots), a CSV whose header
starts with ``"time"``, a ParaView collection and the frame folder beside it holding only its
``.vtu`` frames, and the hidden ``.*.tmp`` files of the atomic writes; anything else (a symbolic
link too) is the user's. A file dropped into ``<out>`` *during* a run is not lost either: a
replaced folder that holds anything else is kept as ``<out>.previous`` with a warning, never
removed; the same holds for the ``<out>.interrupted``, ``<out>.failed`` and ``<out>.killed``
folders a run replaces.

``--out`` must be a folder of its own: not ``/``, not the current folder (``.``) or a folder that
holds it, not the project's own folder or one that holds it; refused with the fix, as is anything
that cannot be resolved (a symbolic-link loop). A ``--out`` that is a symbolic link is followed:
the run works beside and replaces the link's target (``<target>.running``, ``<target>.lock``), so
the link stays a link to the new results and no ``<link>.running`` is left for the next run to
mistake for a killed run.

Everything that can go wrong with the location (a file in the way, no permission, a read-only
file system, a folder that holds files a run did not write) is an :class:`OutputFolderError`
raised by :class:`ResultFolder` or :meth:`ResultFolder.acquire`, before anything runs.
"""
from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import json
import logging
import os
import re
import shutil
from pathlib import Path

from fmu_build.paths import REPO_ROOT
from orchestration.run.status import COMPLETE

logger = logging.getLogger(__name__)

#: the files every run writes under the same name (the others are named by the scene)
FIXED_RESULT_FILES = ("summary.json", "units.json")
#: the project's own folder (a run into it, or into a folder holding it, would replace the project)
PROJECT_DIR = REPO_ROOT
#: how many of a folder's foreign entries a message names
_SHOWN = 5
#: a stream's CSV starts with its quoted header, "time" first (recording.Recorder.add_stream)
_CSV_HEAD = b'"time"'


class OutputFolderError(OSError):
    """The result folder cannot be used; the message names the folder and what to do."""


def _renameat2_exchange():
    """``renameat2(..., RENAME_EXCHANGE)`` from libc, or None (old glibc, not Linux)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        function = libc.renameat2
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    function.restype = ctypes.c_int
    return function


_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths atomically; False when the system cannot (then nothing changed)."""
    function = _renameat2_exchange()
    if function is None:
        return False
    if function(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# -- where a result folder may be --------------------------------------------------------------
def _location_problem(real: Path) -> str | None:
    """Why the resolved ``real`` cannot be a result folder (a run replaces it as a whole), or None."""
    if real.parent == real:
        return "is the root folder of the file system"
    if real == PROJECT_DIR or real in PROJECT_DIR.parents:
        return ("is the project's own folder" if real == PROJECT_DIR
                else f"holds the project's own folder {PROJECT_DIR}")
    try:
        cwd = Path.cwd().resolve()
    except OSError:  # the current folder was removed: nothing to protect there
        return None
    if real == cwd:
        return "is the current folder"
    if real in cwd.parents:
        return f"holds the current folder {cwd}"
    return None


def result_location(out: Path | str) -> Path:
    """The folder a run into ``--out out`` replaces: ``out`` itself, or the target of the
    symbolic link ``out`` (followed, so that the link stays a link). OutputFolderError if ``out``
    cannot be a result folder (see the module docstring)."""
    path = Path(out)
    if not str(out).strip():
        raise OutputFolderError("--out: empty; give a folder, e.g. --out results/mine")
    try:
        real = path.resolve()
        link = path.is_symlink()
    except (OSError, RuntimeError, ValueError) as exc:  # a link loop, a NUL byte, a name too long
        raise OutputFolderError(f"--out {out}: cannot be used as a folder ({exc}): choose another --out, "
                                "e.g. --out results/mine") from None
    problem = _location_problem(real)
    if problem:
        raise OutputFolderError(f"--out {out}: {problem}; a run replaces its --out folder as a whole, so it must be a "
                                "folder of its own: give a new folder, e.g. --out results/mine")
    if link:
        logger.info("--out %s is a symbolic link: the results go to its target %s", out, real)
        return real
    if path.name in ("", ".", ".."):
        return real
    return path


# -- what a run wrote ----------------------------------------------------------------------------
def _read_json(path: Path):
    try:
        with open(path, "rb") as handle:
            return json.load(handle)
    except (OSError, ValueError, RecursionError):
        return None


def _is_summary(path: Path) -> bool:
    summary = _read_json(path)
    return isinstance(summary, dict) and "status" in summary


def _is_units(path: Path) -> bool:
    units = _read_json(path)
    return isinstance(units, dict) and all(isinstance(v, dict) for v in units.values())


def _listed_results(folder: Path) -> set[str]:
    """The file names an earlier run's ``summary.json`` lists as its results (CSVs, .pvd, plots)."""
    summary = _read_json(folder / "summary.json")
    results = summary.get("results") if isinstance(summary, dict) and "status" in summary else None
    if not isinstance(results, dict):
        return set()
    names = set()
    for key, value in results.items():
        if key in ("folder", "surface_errors", "row_errors"):  # the folder itself; messages, not files
            continue
        for item in value if isinstance(value, list) else [value]:
            if isinstance(item, str) and item:
                names.add(Path(item).name)
    return names


def _starts_with(path: Path, head: bytes, within: int = 0) -> bool:
    try:
        with open(path, "rb") as handle:
            data = handle.read(max(len(head), within))
    except OSError:
        return False
    return data.startswith(head) if not within else head in data


def _is_collection(path: Path, listed: set[str]) -> bool:
    """A ParaView collection a run wrote (recording.write_pvd)."""
    if not path.is_file() or path.is_symlink():
        return False
    return path.name in listed or _starts_with(path, b'<VTKFile type="Collection"', within=256)


def _is_result_file(folder: Path, name: str, listed: set[str]) -> bool:
    path = folder / name
    if name.startswith(".") and name.endswith(".tmp"):  # a write that was cut short (_atomic_write_text)
        inner = name[1:-len(".tmp")]
        return inner in FIXED_RESULT_FILES or inner in listed or inner.endswith((".pvd", ".csv"))
    if name == "summary.json":
        return _is_summary(path)
    if name == "units.json":
        return _is_units(path)
    if name.endswith(".pvd"):
        return _is_collection(path, listed)
    if name.endswith(".csv"):
        return name in listed or _starts_with(path, _CSV_HEAD)
    return name in listed  # a plot: only as the summary lists it


def _foreign_frames(frames: Path, series: str) -> list[str]:
    """What in a surface's frame folder is not one of its frames (``<series>_00012.vtu``)."""
    frame = re.compile(rf"\.?{re.escape(series)}_\d+\.vtu(\.tmp)?")
    foreign = []
    with os.scandir(frames) as entries:
        for entry in entries:
            if entry.is_symlink() or not entry.is_file(follow_symlinks=False) or not frame.fullmatch(entry.name):
                foreign.append(f"{series}/{entry.name}" + ("/" if entry.is_dir(follow_symlinks=False) else ""))
    return sorted(foreign)


def foreign_entries(folder: Path | str) -> list[str]:
    """What ``folder`` holds that no run wrote, sorted: ``"my_notes.txt"``, ``"analysis/"``,
    ``"aaa_wall/notes.txt"``; ``[]`` when it holds only results of a run (or nothing).

    Conservative: whatever is not recognised as a run's (see the module docstring) is the user's.
    """
    folder = Path(folder)
    listed = _listed_results(folder)
    foreign = []
    with os.scandir(folder) as scan:
        entries = sorted(scan, key=lambda e: e.name)
    for entry in entries:
        name = entry.name
        if entry.is_symlink():
            foreign.append(name)
        elif entry.is_dir(follow_symlinks=False):
            if _is_collection(folder / f"{name}.pvd", listed):
                foreign.extend(_foreign_frames(folder / name, name))
            else:
                foreign.append(f"{name}/")
        elif not entry.is_file(follow_symlinks=False) or not _is_result_file(folder, name, listed):
            foreign.append(name)
    return foreign


def _shown(entries: list[str]) -> str:
    shown = ", ".join(entries[:_SHOWN])
    return shown + (f", ... ({len(entries)} in all)" if len(entries) > _SHOWN else "")


def _vacant(path: Path) -> Path:
    """``path``, or ``path.2``, ``path.3``, ... : the first that does not exist."""
    candidate, number = path, 1
    while os.path.lexists(candidate):
        number += 1
        candidate = path.with_name(f"{path.name}.{number}")
    return candidate


class ResultFolder:
    """``<out>`` for one run: :meth:`acquire` before, :meth:`publish` at the end, :meth:`release`
    always (``with ResultFolder(out) as folder:`` does the first and the last).

    OutputFolderError at once for an ``out`` that cannot be a result folder (``/``, ``.``, ...)."""

    def __init__(self, out: Path | str):
        #: as the user gave it (messages); ``out`` is where the results go (a link's target)
        self.requested = out
        self.out = result_location(out)
        name = self.out.name
        self.staging = self.out.with_name(f"{name}.running")
        self.lock_path = self.out.with_name(f"{name}.lock")
        self.published: Path | None = None
        self._lock_fd: int | None = None

    def destination(self, status: str) -> Path:
        """Where the results of a run that ended with ``status`` go."""
        if status in COMPLETE:  # its results replace <out>; the others are kept beside it as <out>.<status>
            return self.out
        return self.out.with_name(f"{self.out.name}.{status}")

    def __enter__(self) -> "ResultFolder":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    # -- before the run ------------------------------------------------------------------------
    def acquire(self) -> None:
        """Check the location, take the lock, create ``<out>.running``; OutputFolderError if unusable."""
        try:
            self._acquire()
        except OutputFolderError:
            raise
        except (OSError, ValueError) as exc:  # anything else the file system says (no permission to look, ...)
            where = getattr(exc, "filename", None) or self.out
            raise OutputFolderError(f"--out {self.out}: cannot be used ({getattr(exc, 'strerror', None) or exc}: "
                                    f"{where}): choose an --out in a folder you can write to") from None

    def _acquire(self) -> None:
        out, parent = self.out, self.out.parent
        if out.exists() and not out.is_dir():
            raise OutputFolderError(f"--out {out}: a file of that name is in the way (a run writes a folder): "
                                    "choose another --out or move the file")
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputFolderError(f"--out {out}: cannot create its parent folder {parent} ({exc.strerror or exc}): "
                                    "choose an --out in a folder you can write to") from None
        if not os.access(parent, os.W_OK | os.X_OK):
            raise OutputFolderError(f"--out {out}: its parent folder {parent} is not writable (a run writes "
                                    f"{self.staging.name} beside it and then replaces {out.name}): make it "
                                    f"writable (chmod u+w {parent}) or choose another --out")
        if out.is_dir() and not os.access(out, os.W_OK | os.X_OK):
            raise OutputFolderError(f"--out {out}: the folder is read-only and a run replaces it (its earlier "
                                    f"results are left untouched): make it writable (chmod -R u+w {out}) or "
                                    "choose another --out")
        self._lock()
        try:
            self._check_replaceable()
            self._rescue_killed_run()
            try:
                self.staging.mkdir()
            except OSError as exc:
                raise OutputFolderError(f"--out {out}: cannot create {self.staging} ({exc.strerror or exc}): "
                                        "choose an --out in a folder you can write to") from None
        except BaseException:
            self.release()
            raise

    def _lock(self) -> None:
        while True:
            try:
                # O_NOFOLLOW: a link named <out>.lock must not make us truncate the file it points to
                fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o644)
            except OSError as exc:
                raise OutputFolderError(f"--out {self.out}: cannot create the lock file {self.lock_path} "
                                        f"({exc.strerror or exc}): the location is not writable (a read-only file "
                                        "system?) or something else has that name; choose an --out you can write "
                                        "to") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                owner = _read_pid(fd)
                os.close(fd)
                who = f"pid {owner}" if owner else "another process"
                raise OutputFolderError(f"--out {self.out} is in use by another run ({who}, lock {self.lock_path}): "
                                        "wait for it to finish or choose another --out") from None
            # The holder before us may have removed the file between our open and our flock: then
            # we hold a lock on a file nobody else sees. Only the file at the path counts.
            try:
                same = os.stat(self.lock_path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        if not _is_lock_file(fd):
            # a file of the user's that happens to be named <out>.lock: we truncate and remove our lock
            os.close(fd)
            raise OutputFolderError(f"--out {self.out}: {self.lock_path} is in the way and is not the lock of a run "
                                    "(a run writes its PID there and removes it at its end): move that file or "
                                    "choose another --out")
        previous = _read_pid(fd)
        if previous and previous != os.getpid():
            state = "no longer running" if not _pid_alive(previous) else "running but no longer holding it"
            logger.warning("--out %s: took over the lock of an earlier run (pid %d, %s)", self.out, previous, state)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._lock_fd = fd

    def _check_replaceable(self) -> None:
        """``<out>`` is replaced as a whole: refuse a folder that holds anything a run did not write."""
        out = self.out
        if not out.is_dir():
            return
        foreign = foreign_entries(out)
        if foreign:
            raise OutputFolderError(f"--out {out} holds files that are not results of a run ({_shown(foreign)}); a "
                                    "run replaces its --out folder as a whole and would delete them: move them out "
                                    f"of {out}, or choose a new or empty folder for --out")

    def _rescue_killed_run(self) -> None:
        """A ``<out>.running`` left by a killed run holds its rows: keep it as ``<out>.killed``."""
        if not os.path.lexists(self.staging):
            return
        killed = self.out.with_name(f"{self.out.name}.killed")
        if os.path.lexists(killed):
            self._discard(killed)
        os.replace(self.staging, killed)
        logger.warning("--out %s: an earlier run was killed before it finished; its results were moved to %s",
                       self.out, killed)

    def _discard(self, old: Path) -> None:
        """Remove ``old``, a folder of results this run replaces; one that holds anything a run did
        not write (put there while this run ran) is kept as ``<out>.previous`` instead."""
        try:
            foreign = ["(a symbolic link)"] if old.is_symlink() else foreign_entries(old)
        except OSError as exc:
            foreign = [f"(unreadable: {exc.strerror or exc})"]
        if not foreign:
            shutil.rmtree(old, ignore_errors=True)
            if not os.path.lexists(old):
                return
            foreign = ["(files that could not be removed)"]
        kept = _vacant(self.out.with_name(f"{self.out.name}.previous"))
        try:
            os.replace(old, kept)
        except OSError as exc:  # the results are published already: a warning, not a failed run
            logger.warning("--out %s: the replaced folder held %s, which no run wrote; it was left as %s (%s)",
                           self.out, _shown(foreign), old, exc.strerror or exc)
            return
        logger.warning("--out %s: the replaced folder held %s, which no run wrote; it was kept as %s",
                       self.out, _shown(foreign), kept)

    # -- after the run -------------------------------------------------------------------------
    def publish(self, status: str) -> Path:
        """Move ``<out>.running`` to :meth:`destination` (replacing what is there); return it."""
        dest = self.destination(status)
        if os.path.lexists(dest):
            if not dest.is_symlink() and dest.is_dir() and exchange(self.staging, dest):
                old = self.staging  # now holds what was at dest
            else:
                # never a fixed name such as <dest>.old, which could be a folder of the user's
                old = _vacant(dest.with_name(f".{dest.name}.replaced"))
                os.replace(dest, old)
                os.replace(self.staging, dest)
            self._discard(old)
        else:
            os.replace(self.staging, dest)
        self.published = dest
        return dest

    def release(self) -> None:
        """Drop the lock (and its file). A staging folder still there (publish failed) is kept."""
        if self._lock_fd is None:
            return
        fd, self._lock_fd = self._lock_fd, None
        with contextlib.suppress(OSError):
            os.unlink(self.lock_path)  # while still holding it: see _lock
        os.close(fd)
        if self.published is None and self.staging.exists():
            try:
                self.staging.rmdir()  # empty: nothing ran (a scene or argument error)
            except OSError:
                logger.warning("the results of this run were left in %s", self.staging)


def _is_lock_file(fd: int) -> bool:
    """The file is empty (just created) or holds a PID: a run's lock, not a file of the user's."""
    try:
        size = os.fstat(fd).st_size
        text = os.pread(fd, 32, 0).decode("ascii").strip() if size else ""
    except (OSError, UnicodeDecodeError):
        return False
    return size <= 32 and (not text or text.isdigit())


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
        return int(text) if text else None
    except (OSError, ValueError):
        return None

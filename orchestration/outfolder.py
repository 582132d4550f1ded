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

Everything that can go wrong with the location (a file in the way, no permission, a read-only
file system, a folder that does not look like results) is an :class:`OutputFolderError` raised
by :meth:`ResultFolder.acquire`, before anything runs.
"""
from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import logging
import os
import shutil
from pathlib import Path

logger = logging.getLogger(__name__)

#: statuses whose results replace ``<out>``; the others are kept beside it as ``<out>.<status>``
COMPLETE_STATUSES = ("completed", "terminated")
#: what makes an existing non-empty folder recognisable as results (written first by every run)
_RESULT_MARKERS = ("summary.json", "units.json")


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


class ResultFolder:
    """``<out>`` for one run: :meth:`acquire` before, :meth:`publish` at the end, :meth:`release`
    always (``with ResultFolder(out) as folder:`` does the first and the last)."""

    def __init__(self, out: Path | str):
        self.out = Path(out)
        name = self.out.name
        if not name or name in (".", ".."):
            self.out = self.out.resolve()
            name = self.out.name
        self.staging = self.out.with_name(f"{name}.running")
        self.lock_path = self.out.with_name(f"{name}.lock")
        self.published: Path | None = None
        self._lock_fd: int | None = None

    def destination(self, status: str) -> Path:
        """Where the results of a run that ended with ``status`` go."""
        if status in COMPLETE_STATUSES:
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
        except OSError as exc:  # anything else the file system says (no permission to look, ...)
            where = exc.filename or self.out
            raise OutputFolderError(f"--out {self.out}: cannot be used ({exc.strerror or exc}: {where}): "
                                    "choose an --out in a folder you can write to") from None

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
                fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except OSError as exc:
                raise OutputFolderError(f"--out {self.out}: cannot create the lock file {self.lock_path} "
                                        f"({exc.strerror or exc}): the location is not writable (a read-only file "
                                        "system?); choose an --out you can write to") from None
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
        previous = _read_pid(fd)
        if previous and previous != os.getpid():
            state = "no longer running" if not _pid_alive(previous) else "running but no longer holding it"
            logger.warning("--out %s: took over the lock of an earlier run (pid %d, %s)", self.out, previous, state)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._lock_fd = fd

    def _check_replaceable(self) -> None:
        """``<out>`` is replaced as a whole: refuse a folder that holds anything but results."""
        out = self.out
        if not out.is_dir():
            return
        entries = sorted(p.name for p in out.iterdir())
        if entries and not any(marker in entries for marker in _RESULT_MARKERS):
            shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
            raise OutputFolderError(f"--out {out} holds files that are not results of a run ({shown}); a run "
                                    "replaces its --out folder as a whole: choose a new or empty folder")

    def _rescue_killed_run(self) -> None:
        """A ``<out>.running`` left by a killed run holds its rows: keep it as ``<out>.killed``."""
        if not self.staging.exists():
            return
        killed = self.out.with_name(f"{self.out.name}.killed")
        if killed.exists():
            shutil.rmtree(killed, ignore_errors=True)
        os.replace(self.staging, killed)
        logger.warning("--out %s: an earlier run was killed before it finished; its results were moved to %s",
                       self.out, killed)

    # -- after the run -------------------------------------------------------------------------
    def publish(self, status: str) -> Path:
        """Move ``<out>.running`` to :meth:`destination` (replacing what is there); return it."""
        dest = self.destination(status)
        if dest.exists():
            if exchange(self.staging, dest):
                old = self.staging  # now holds what was at dest
            else:
                old = dest.with_name(f"{dest.name}.old")
                shutil.rmtree(old, ignore_errors=True)
                os.replace(dest, old)
                os.replace(self.staging, dest)
            shutil.rmtree(old, ignore_errors=True)
            if old.exists():
                logger.warning("could not remove the earlier results, moved to %s", old)
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


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
        return int(text) if text else None
    except (OSError, ValueError):
        return None

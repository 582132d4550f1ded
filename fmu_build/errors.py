"""The build's error: which step failed and the fix."""
from __future__ import annotations

from pathlib import Path


class BuildError(RuntimeError):
    """A build step failed; the message names the step and the fix."""


def unwritable(step: str, exc: OSError, folder: Path) -> BuildError:
    """The BuildError of a build step that could not write (or read) a file in ``folder``: a
    read-only checkout, one owned by another user, a full disk. Names the file and the fix."""
    where = exc.filename if exc.filename is not None else folder
    return BuildError(f"{step}: cannot write {where} ({exc.strerror or exc}). The build writes into {folder}: run "
                      f"`python -m orchestration build` once as a user who may write there (the owner of the "
                      f"checkout), or use a checkout of your own")

"""Run directories that tell the truth: never a new run's results beside an old run's files.

`prepare_run_dir` is called by `simulate`, `run` and `sweep` before anything flies:
a non-empty directory is refused unless the user asks for `--overwrite`; the directory
must be writable (checked by writing a probe file), so a long run is never lost at the
end to a permission error.

`--overwrite` deletes only run artefacts: the files and directories runs write
(RUN_FILES, RUN_SUFFIXES, RUN_PREFIXES, RUN_DIRS, RUN_DIR_PREFIXES) and the MARKER
every run directory gets. A directory that holds anything else (notes, a subfolder
someone added, a source tree) is refused, whether it carries the marker or not, and
the message names the entries that are not a run's; nothing is deleted then.

Some directories are never a run directory, even empty: the file-system root, the
system's temporary directory (`tempfile.gettempdir()`, `/tmp`, `/var/tmp`), the home
directory, the current directory, and any parent of these (PROTECTED_WHY). A run goes
into a directory of its own (`--out /tmp/myrun`, not `--out /tmp`).
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

MARKER = ".swarmdrop-run"
"""Written into every run directory (a run artefact like the others)."""
RUN_FILES = frozenset({"metrics.json", "config.json", "run.json", "telemetry.npz", "ports.json", "sitl.tlog",
                       "sitl.log", "signing.key", "launch_so3.csv", "runs.csv", "summary.md", "summary.json", MARKER})
RUN_SUFFIXES = (".png", ".tlog", ".timestamp")
RUN_PREFIXES = ("signing.key.timestamp", ".write-test-")
"""Files named so: the signing timestamps of the SITL and of each agent (signing.key.timestamp-3,
and their .tmp while being replaced), the writability probe."""
RUN_DIRS = frozenset({"agents", "failures"})
RUN_DIR_PREFIXES = ("rerun_",)
"""Directories named so: `sweep --rerun SEED` runs inside a sweep's directory."""
SYSTEM_TEMP_DIRS = ("/tmp", "/var/tmp")


class RunDirError(ValueError):
    """The run directory cannot be used; the message says why and what to do."""


def is_run_artefact(entry: Path) -> bool:
    """entry (a child of a run directory) is something a run writes (its name says so;
    a symlink counts as a file, never as one of the run's directories)."""
    name = entry.name
    if entry.is_dir() and not entry.is_symlink():
        return name in RUN_DIRS or name.startswith(RUN_DIR_PREFIXES)
    return name in RUN_FILES or name.endswith(RUN_SUFFIXES) or name.startswith(RUN_PREFIXES)


def _resolved(path: str | Path) -> Path | None:
    try:
        return Path(path).expanduser().resolve()
    except (OSError, RuntimeError):  # (no home directory, a symlink loop)
        return None


def protected_why(path: Path) -> str | None:
    """Why path (resolved) may never be a run directory, even empty; None if it may be."""
    if path == Path(path.anchor):
        return "it is the file-system root"
    places = [("the system's temporary directory", p) for p in (tempfile.gettempdir(), *SYSTEM_TEMP_DIRS)]
    places += [("your home directory", "~"), ("the current directory", ".")]
    for what, place in places:
        resolved = _resolved(place)
        if resolved is None:
            continue
        if path == resolved:
            return f"it is {what}"
        if resolved.is_relative_to(path):
            return f"it contains {what} ({resolved})"
    return None


def _refuse_to_clear(path: Path) -> str | None:
    """Why --overwrite may not clear path (None: everything in it is a run's artefact)."""
    if (path / ".git").exists() or (path / "pyproject.toml").exists():
        return "it looks like a source tree (it has .git or pyproject.toml)"
    other = sorted(child.name + ("/" if child.is_dir() and not child.is_symlink() else "")
                   for child in path.iterdir() if not is_run_artefact(child))
    if other:
        shown = ", ".join(other[:10]) + (f" and {len(other) - 10} more" if len(other) > 10 else "")
        return (f"it holds {len(other)} entr{'y' if len(other) == 1 else 'ies'} that no run writes ({shown}); "
                "--overwrite deletes only a run's files: move those away, or choose another --out")
    return None


def prepare_run_dir(out_dir: str | Path, overwrite: bool = False) -> Path:
    """Make out_dir ready for a new run and return it resolved.

    A missing directory is created; an empty one (or one holding only the MARKER: a run
    that wrote nothing) is used as it is; a non-empty one is
    refused, or with overwrite cleared first if it holds only run artefacts (never a
    directory with anything else in it, nor a source tree). A protected directory
    (protected_why: the root, a system temporary directory, the home or current
    directory, or a parent of one) is refused even when empty. The directory gets the MARKER.

    Raises:
        RunDirError: out_dir is a file, is protected, is not empty (and overwrite is False),
            may not be cleared, or cannot be created or written; the message names it and says why.
    """
    path = Path(out_dir).expanduser().resolve()
    if path.exists() and not path.is_dir():
        raise RunDirError(f"--out {out_dir}: exists and is not a directory")
    why = protected_why(path)
    if why is not None:
        raise RunDirError(f"--out {out_dir}: cannot be a run directory: {why}; give the run a directory of its own, "
                          f"e.g. --out {path / 'run'}")
    # (a directory holding only the MARKER is a run that wrote nothing: failed at start or was
    # interrupted, and said so; it is used as it is)
    if path.is_dir() and any(child.name != MARKER for child in path.iterdir()):
        if not overwrite:
            raise RunDirError(f"--out {out_dir}: the directory is not empty (a previous run?); pass --overwrite to "
                              "clear it first, or choose another --out")
        why = _refuse_to_clear(path)
        if why is not None:
            raise RunDirError(f"--out {out_dir}: refusing to clear it with --overwrite: {why}")
        try:
            for child in path.iterdir():
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child)
                else:
                    child.unlink()
        except OSError as err:
            raise RunDirError(f"--out {out_dir}: cannot clear it: {err.strerror or err}") from None
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-test-", dir=path)
        os.close(fd)
        os.unlink(probe)
        (path / MARKER).write_text("A swarmdrop run directory: `--overwrite` may delete the files runs write here.\n")
    except OSError as err:
        raise RunDirError(f"--out {out_dir}: cannot write there: {err.strerror or err}") from None
    return path


def interrupted_note(out_dir: Path, finished: str | None = None) -> str:
    """The one line to print when a run into out_dir is interrupted: what it holds.

    Args:
        finished: the file written last, whose presence means the results are complete
            (simulate's metrics.json), or None.
    """
    try:
        left = sorted(p.name for p in out_dir.iterdir() if p.name != MARKER and not p.name.startswith(".write-test-"))
    except OSError:
        left = []
    if not left:
        return f"interrupted: nothing was written to {out_dir}"
    if finished is not None and finished in left:
        return f"interrupted after the results were written: {out_dir} holds the whole run"
    shown = ", ".join(left[:6]) + (", ..." if len(left) > 6 else "")
    return (f"interrupted: {out_dir} holds an incomplete run ({shown}); run the same command again with "
            "--overwrite to redo it")

"""Every output path a command is given is checked before anything runs (exit 2 naming
the option, the path and why), so that no run is simulated only to be lost at the end:
``omnifleet run paper --in-process --out /proc/x`` simulated the whole run, then died in
``write_run`` with a ``FileNotFoundError``.

A path is writable when a file can really be created where it will go: the folder
itself if it exists, else its nearest existing ancestor (where it will be created). The
check creates a probe file there and removes it at once: permission bits say nothing for
root, nor about read-only or virtual file systems (``/proc``, ``/sys``).

:func:`rescue_folder`: where a run's results go when its folder cannot be written at the
end after all (it vanished, or became a file, while the run went): a new folder under the
temporary directory, which the command names.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

PROBE = ".omnifleet-write-check"


class OutputPathError(ValueError):
    """An output path that cannot be written (exit code 2 at the CLI)."""


def _existing_ancestor(path: Path) -> Path:
    for p in (path, *path.parents):
        if p.exists():
            return p
    return Path(".")


def _probe(folder: Path) -> str | None:
    """Why a file cannot be created in ``folder`` (None: it can)."""
    probe = folder / f"{PROBE}-{os.getpid()}"
    try:
        with open(probe, "x"):
            pass
    except OSError as exc:
        return exc.strerror or str(exc)
    try:
        probe.unlink()
    except OSError:
        pass
    return None


def check_folder(path: str | Path, option: str) -> Path:
    """``path`` as a folder the command can fill (created later, with its parents, if
    missing). Raises :class:`OutputPathError` naming ``option``, the path and why."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputPathError(f"{option} {path}: exists and is not a folder")
    where = _existing_ancestor(path)
    if not where.is_dir():
        raise OutputPathError(f"{option} {path}: {where} is a file, so the folder cannot be "
                              "created there")
    why = _probe(where)
    if why is not None:
        what = "cannot write in it" if where == path else f"cannot create it in {where}"
        raise OutputPathError(f"{option} {path}: {what} ({why})")
    return path


def check_file(path: str | Path, option: str) -> Path:
    """``path`` as a file the command can write (its folder created later if missing).
    Raises :class:`OutputPathError` naming ``option``, the path and why."""
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(f"{option} {path}: is a folder; give a file name")
    folder = path.parent
    if folder.exists() and not folder.is_dir():
        raise OutputPathError(f"{option} {path}: {folder} is not a folder")
    where = _existing_ancestor(folder)
    why = "is a file" if not where.is_dir() else _probe(where)
    if why is not None:
        raise OutputPathError(f"{option} {path}: cannot write in {where} ({why})")
    if path.exists() and not os.access(path, os.W_OK):
        raise OutputPathError(f"{option} {path}: exists and cannot be written")
    return path


def rescue_folder(name: str) -> Path:
    """A fresh folder under the temporary directory for results whose own folder could
    not be written: ``<tmp>/omnifleet-rescued-<name>-<time>-XXXX``."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path(tempfile.mkdtemp(prefix=f"omnifleet-rescued-{name}-{stamp}-"))


def usable_folder(path: str | Path, name: str) -> tuple[Path, str | None]:
    """``path`` (created if missing) when a file can be created in it now; else a
    :func:`rescue_folder` and why ``path`` could not be used."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        why = _probe(path)
    except OSError as exc:
        why = exc.strerror or str(exc)
    if why is None:
        return path, None
    return rescue_folder(name), why

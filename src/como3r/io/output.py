"""Output folders that appear only when complete, and replace only what como3r wrote.

A run writes into ``<out>.partial`` and renames it to ``<out>`` at the end, so an
interrupted or failed run never leaves a folder that looks like a result. Every folder
written this way holds a marker file, :data:`MARKER` (JSON: como3r version, command line,
time). ``overwrite`` replaces only a folder with that marker; any other non-empty folder is
refused, so ``--overwrite`` never deletes a user's files. The old folder is swapped out only
once the new one is complete: ``<out>`` -> ``<out>.old-<pid>``, ``<out>.partial`` ->
``<out>``, then the old one is deleted; if the swap fails the old folder is put back.

A killed run leaves ``<out>.partial`` behind; ``resume`` continues in it (``como3r run
--resume``: its session store) instead of starting afresh, and keeps it if the resumed run
fails too. An interrupted run (Ctrl-C, SIGTERM, a full disk) keeps it too where it holds work
that only ``--overwrite`` may delete (``kept``: a session store with keyframes), and a new
run without ``resume`` or ``overwrite`` refuses to replace such a folder.
"""

from __future__ import annotations

import datetime
import errno
import json
import os
import shlex
import shutil
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from como3r import __version__
from como3r.errors import InputError

#: name of the marker file in every folder como3r writes
MARKER = ".como3r-run"


def is_como3r_output(folder: str | Path) -> bool:
    """Whether ``folder`` holds the marker of a folder como3r wrote."""
    return (Path(folder) / MARKER).is_file()


#: whether a staging folder holds work that only ``--overwrite`` deletes
Kept = Callable[[Path], bool]


def staging_dir(out: str | Path) -> Path:
    """The staging folder ``<out>.partial`` of an output folder ``out``."""
    return _staging(Path(out))


#: ``sqlite3.SQLITE_FULL``: an insert failed because the disk is full
_SQLITE_FULL = 13


def is_disk_full(exc: BaseException | None) -> bool:
    """Whether ``exc``, or an error it was raised from or while handling, is a full disk or
    quota: ``ENOSPC``/``EDQUOT``, or SQLite's ``SQLITE_FULL`` (a session store's write)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if getattr(exc, "sqlite_errorcode", None) == _SQLITE_FULL:
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def check_output_dir(
    out: str | Path, overwrite: bool = False, resume: bool = False, kept: Kept | None = None
) -> None:
    """Refuse, before any work, an ``out`` that a run could not write.

    Args:
        kept: whether a staging folder holds work (an interrupted run's session store)
            that a new run replaces only with ``overwrite``.

    Raises:
        InputError: ``out`` is not a folder; or is a non-empty folder and ``overwrite`` is
            false; or is a non-empty folder without the como3r marker (never replaced); or
            a staging folder ``<out>.partial`` without the marker is in the way; or
            (``resume``) there is no staging folder written by como3r to continue in; or
            (neither ``resume`` nor ``overwrite``) one that ``kept`` says holds work.
    """
    out = Path(out)
    _check_target(out, overwrite)
    staging = _staging(out)
    if resume and not is_como3r_output(staging):
        raise InputError(
            f"{out}: nothing to resume ({staging} does not exist or was not written by como3r)"
        )
    if (staging.exists() or staging.is_symlink()) and not is_como3r_output(staging):
        raise InputError(
            f"{staging}: not written by como3r; refusing to delete it (it has "
            f"no {MARKER} file): move it away or choose another --out"
        )
    if not (resume or overwrite) and kept is not None and staging.is_dir() and kept(staging):
        raise InputError(
            f"{staging}: holds the session store of an interrupted run: continue "
            f"it with --resume, or start afresh with --overwrite (which deletes "
            f"it)"
        )


def _check_target(out: Path, overwrite: bool) -> None:
    if out.exists() or out.is_symlink():
        if out.is_symlink() or not out.is_dir():
            raise InputError(f"{out}: exists and is not a folder")
        if any(out.iterdir()):
            if not overwrite:
                raise InputError(f"{out}: output folder exists and is not empty (use --overwrite)")
            if not is_como3r_output(out):
                raise InputError(
                    f"{out}: not written by como3r; refusing to overwrite (it has no {MARKER} file)"
                )


def _staging(out: Path) -> Path:
    return out.with_name(out.name + ".partial")


def command_line(*extra: str) -> str:
    """The running command line as a user would type it, shell-quoted, with ``extra``
    arguments after it."""
    return shlex.join([*_program(), *sys.argv[1:], *extra])


def _program() -> list[str]:
    """How the running program was started, as a user would type it: ``python -m
    como3r.cli`` runs the module file, whose name (``cli.py``) nobody types."""
    name = Path(sys.argv[0]).name
    return ["python", "-m", "como3r.cli"] if name == "cli.py" else [name]


def _write_marker(folder: Path) -> None:
    marker = {
        "como3r": __version__,
        "command": command_line(),
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    (folder / MARKER).write_text(json.dumps(marker) + "\n")


def _swap_in(staging: Path, out: Path) -> None:
    """Make the complete ``staging`` folder ``out``, deleting a previous ``out`` last."""
    if not out.exists():
        staging.rename(out)
        return
    if not any(out.iterdir()):
        out.rmdir()
        staging.rename(out)
        return
    old = out.with_name(f"{out.name}.old-{os.getpid()}")
    out.rename(old)
    try:
        staging.rename(out)
    except BaseException:
        old.rename(out)
        raise
    shutil.rmtree(old)


@contextmanager
def atomic_output_dir(
    out: str | Path, overwrite: bool = False, resume: bool = False, kept: Kept | None = None
) -> Iterator[Path]:
    """Yield a staging folder that becomes ``out`` only if the block succeeds.

    The staging folder carries the marker from the start, so a staging folder left by a
    killed run is recognised (and replaced) by the next one, or with ``resume`` continued
    in. On failure it is deleted (kept when resuming, and when the block was interrupted
    by a ``KeyboardInterrupt`` and ``kept`` says it holds work) and an existing ``out`` is
    left as it was.

    Raises:
        InputError: as :func:`check_output_dir`.
    """
    out = Path(out)
    check_output_dir(out, overwrite, resume, kept)
    staging = _staging(out)
    if staging.exists() and not resume:
        shutil.rmtree(staging)
    staging.mkdir(parents=True, exist_ok=resume)
    try:
        _write_marker(staging)
        yield staging
    except BaseException as exc:
        # interrupts and a full disk end a run alike: what it did is kept, resumable
        interrupted = isinstance(exc, KeyboardInterrupt) or is_disk_full(exc)
        if not (resume or (interrupted and kept is not None and kept(staging))):
            shutil.rmtree(staging, ignore_errors=True)
        raise
    try:
        _check_target(out, overwrite)  # again: the run may have taken hours
    except InputError as exc:
        raise InputError(f"{exc}; the new output is in {staging}") from None
    _swap_in(staging, out)

"""Output folders that appear only when complete.

A run writes into ``<out>.partial`` and renames it to ``<out>`` at the end, so an
interrupted or failed run never leaves a folder that looks like a result.
"""

from __future__ import annotations

import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from como3r.errors import InputError


@contextmanager
def atomic_output_dir(out: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a staging folder that becomes ``out`` only if the block succeeds.

    Raises:
        InputError: ``out`` exists (and ``overwrite`` is false) or is not a folder.
    """
    out = Path(out)
    if out.exists():
        if not out.is_dir():
            raise InputError(f"{out}: exists and is not a folder")
        if any(out.iterdir()) and not overwrite:
            raise InputError(f"{out}: output folder exists and is not empty (use --overwrite)")
    staging = out.with_name(out.name + ".partial")
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out)
    staging.rename(out)

"""``como3r weights``: fetch, list and locate the MASt3R weight files
(:mod:`como3r.prior.weights`)."""

from __future__ import annotations

import typer
from rich.progress import (
    BarColumn,
    DownloadColumn,
    TextColumn,
    TimeRemainingColumn,
    TransferSpeedColumn,
)

from como3r.cli_common import (
    Command,
    OneLineErrorsGroup,
    console,
    on_interrupt,
    print_rows,
    user_errors,
)
from como3r.cli_progress import QUIET_HELP, run_progress
from como3r.prior import weights

weights_app = typer.Typer(
    cls=OneLineErrorsGroup,
    no_args_is_help=True,
    help="The MASt3R checkpoint, retrieval head and codebook.",
)


@weights_app.command("fetch", cls=Command)
@on_interrupt(
    lambda kwargs: (
        "interrupted: what was downloaded is kept as <file>.part in "
        f"{weights.weights_home()}; `como3r weights fetch` resumes it"
    )
)
@user_errors
def fetch(
    trust_unverified: bool = typer.Option(
        False,
        "--trust-unverified",
        help="Accept files for which no official SHA-256 is published (today: all three); "
        "their computed SHA-256 is printed.",
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=QUIET_HELP),
) -> None:
    """Download the three files into the weights cache (resumes a broken download)."""
    weights.check_trust(weights.WEIGHT_FILES, trust_unverified)
    home, url = weights.weights_home(), weights.base_url()
    console.print(f"weights cache: {home}\nsource: {url}", highlight=False, soft_wrap=True)
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        DownloadColumn(),
        TransferSpeedColumn(),
        TimeRemainingColumn(),
    )
    with run_progress(quiet, columns) as shown:
        statuses = [
            weights.fetch_file(
                file, home, url, trust_unverified, progress=shown.steps(file.role, unit=_size)
            )
            for file in weights.WEIGHT_FILES
        ]
    for status in statuses:
        console.print(
            f"{status.file.filename}: {status.state}, sha256 {status.sha256}",
            highlight=False,
            soft_wrap=True,
        )


@weights_app.command("list", cls=Command)
@user_errors
def list_files(
    check: bool = typer.Option(
        False,
        "--check",
        help="Recompute every SHA-256 instead of reading the one recorded at fetch.",
    ),
) -> None:
    """What the weights cache holds: each file's size and whether it is verified."""
    home = weights.weights_home()
    rows = [
        {
            "file": s.file.role,
            "size": _size(s.size),
            "state": s.state,
            "sha256": f"{s.sha256[:16]}..." if s.sha256 else "-",
        }
        for s in (weights.file_status(f, home, rehash=check) for f in weights.WEIGHT_FILES)
    ]
    console.print(f"weights cache: {home}", highlight=False, soft_wrap=True)
    print_rows("MASt3R weights", rows)


@weights_app.command("path", cls=Command)
def path() -> None:
    """Print the weights cache folder (COMO3R_HOME)."""
    console.print(str(weights.weights_home()), highlight=False, soft_wrap=True)


def _size(size: int) -> str:
    """Bytes in the largest unit that keeps a leading digit (decimal units)."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if size >= scale:
            return f"{size / scale:.1f} {unit}"
    return f"{size} B"

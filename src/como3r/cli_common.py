"""What every ``como3r`` command shares: one-line errors, Ctrl-C handling, progress bars,
tables, and a help text without metavars on flags (``--calib``, not ``--calib <bool>``).

Both :mod:`como3r.cli` and :mod:`como3r.cli_weights` import it, so ``python -m como3r.cli``
works (the two command modules do not import each other in a cycle).
"""

from __future__ import annotations

import contextlib
import functools
import re
import signal
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeElapsedColumn,
)
from rich.table import Table
from typer.core import TyperCommand, TyperGroup

from como3r.errors import Como3rError

try:  # typer >= 0.26 carries its own copy of click
    from typer._click import exceptions as click_exceptions
except ImportError:  # pragma: no cover - older typer on the click package
    from click import exceptions as click_exceptions  # type: ignore[no-redef]

console = Console()
err_console = Console(stderr=True)

F = TypeVar("F", bound=Callable[..., None])

EXIT_USER_ERROR = 2
#: 128 + SIGINT, what a shell reports for a command stopped by Ctrl-C
EXIT_INTERRUPTED = 130


def print_error(message: str) -> None:
    """``error: message`` as one line on stderr (line breaks in ``message`` become spaces)."""
    line = " ".join(message.split())
    err_console.print(f"[bold red]error:[/] {escape(line)}", highlight=False, soft_wrap=True)


class OneLineErrorsGroup(TyperGroup):
    """The command group; a command line click cannot parse (a missing or unknown option, a
    value of the wrong type, an unknown command) is one ``error:`` line and exit status 2,
    not click's usage box. ``como3r`` alone still prints the help."""

    def make_context(self, info_name, args, parent=None, **extra):  # type: ignore[no-untyped-def]
        with _usage_errors_in_one_line():
            return super().make_context(info_name, args, parent=parent, **extra)

    def invoke(self, ctx):  # type: ignore[no-untyped-def]
        with _usage_errors_in_one_line():
            return super().invoke(ctx)

    def get_params(self, ctx):  # type: ignore[no-untyped-def]
        return _without_flag_metavars(super().get_params(ctx))


def _without_flag_metavars(params: list[Any]) -> list[Any]:
    """Options that take no value (flags, ``--help``) show no ``<bool>`` in the help."""
    for param in params:
        if getattr(param, "is_flag", False) or getattr(param, "count", False):
            param.metavar = ""
    return params


class Command(TyperCommand):
    """A command whose flags show no metavar in ``--help``, and whose usage line names its
    positional arguments as a user types them (``merge [OPTIONS] A B``, not typer's
    ``{A} {B}``)."""

    def get_params(self, ctx):  # type: ignore[no-untyped-def]
        return _without_flag_metavars(super().get_params(ctx))

    def collect_usage_pieces(self, ctx):  # type: ignore[no-untyped-def]
        return [_REQUIRED_BRACES.sub(r"\1", piece) for piece in super().collect_usage_pieces(ctx)]


#: typer's usage piece of a required argument, ``{NAME}`` (``{NAME}...`` for several)
_REQUIRED_BRACES = re.compile(r"^\{(.*)\}(?=(?:\.\.\.)?$)")


@contextlib.contextmanager
def _usage_errors_in_one_line() -> Iterator[None]:
    """Turn click's usage errors inside the block into one ``error:`` line and status 2."""
    try:
        yield
    except click_exceptions.ClickException as exc:
        if isinstance(exc, getattr(click_exceptions, "NoArgsIsHelpError", ())):
            raise  # click >= 8.2: `como3r` alone prints the help this way
        hint = ""
        ctx = getattr(exc, "ctx", None)
        if ctx is not None:
            hint = f" (see: {ctx.command_path} --help)"
        print_error(f"{exc.format_message()}{hint}")
        raise typer.Exit(EXIT_USER_ERROR) from None


def user_errors(func: F) -> F:
    """Report a :class:`Como3rError`, or an operating-system error on a file the user named
    (a folder that cannot be created, a full disk), as one line and exit with status 2."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except Como3rError as exc:
            print_error(str(exc) + _kept_on_full_disk(exc, kwargs))
            raise typer.Exit(EXIT_USER_ERROR) from None
        except OSError as exc:
            where = f"{exc.filename}: " if exc.filename is not None else ""
            print_error(f"{where}{exc.strerror or exc}" + _kept_on_full_disk(exc, kwargs))
            raise typer.Exit(EXIT_USER_ERROR) from None

    return wrapper  # type: ignore[return-value]


def on_interrupt(message: Callable[[dict[str, Any]], str]) -> Callable[[F], F]:
    """Ctrl-C in the decorated command prints ``message(kwargs)`` as one line (what was and
    was not written) and exits with status 130 (143 for a run stopped by SIGTERM at a
    checkpoint, :class:`~como3r.runtime.interrupts.RunInterrupted`)."""

    def decorate(func: F) -> F:
        @functools.wraps(func)
        def wrapper(*args, **kwargs):
            try:
                return func(*args, **kwargs)
            except KeyboardInterrupt as exc:
                err_console.print(message(kwargs), markup=False, highlight=False, soft_wrap=True)
                signum = getattr(exc, "signum", signal.SIGINT)
                raise typer.Exit(128 + signum) from None

        return wrapper  # type: ignore[return-value]

    return decorate


#: for a command that writes ``--out`` through :func:`~como3r.io.output.atomic_output_dir`:
#: the staging folder is gone and an earlier output untouched
interrupt_leaves_nothing = on_interrupt(
    lambda kwargs: f"interrupted: nothing was written to {kwargs['out']}"
)


def _kept_on_full_disk(exc: BaseException, kwargs: dict[str, Any]) -> str:
    """For a run stopped by a full disk that kept its session store: how to continue it."""
    from como3r.io.output import command_line, is_disk_full, staging_dir

    if kwargs.get("out") is None or not is_disk_full(exc):
        return ""
    from como3r.store.schema import STORE_NAME

    staging = staging_dir(kwargs["out"])
    if not (staging / STORE_NAME).is_file():
        return ""
    resume = () if kwargs.get("resume") else ("--resume",)
    return (
        f"; the session store in {staging} is kept: free some space and continue "
        f"with: {command_line(*resume)}"
    )


def _store_kept_or_nothing(kwargs: dict[str, Any]) -> str:
    """What an interrupted ``run`` or ``coordinator`` left: its session store in
    ``OUT.partial`` and the exact command that continues it, or nothing."""
    from como3r.io.output import command_line, staging_dir
    from como3r.store.schema import STORE_NAME

    staging = staging_dir(kwargs["out"])
    if not (staging / STORE_NAME).is_file():
        return f"interrupted: nothing was written to {kwargs['out']}"
    resume = () if kwargs.get("resume") else ("--resume",)
    return (
        f"interrupted: the session store in {staging} is kept; continue with: "
        f"{command_line(*resume)}"
    )


#: for ``run`` and ``coordinator``: an interrupted run keeps ``OUT.partial`` with its
#: session store where it holds work (:mod:`como3r.runtime.interrupts`)
interrupt_keeps_the_store = on_interrupt(_store_kept_or_nothing)


@contextlib.contextmanager
def progress_bar(*columns: ProgressColumn, shown: bool = True) -> Iterator[Progress]:
    """A rich progress bar for long work: shown only on a terminal (a log file or pipe gets
    no bar) and when ``shown``, and erased when the work fails or is interrupted, so that
    the ``error:`` or ``interrupted:`` line is all that remains.

    Args:
        columns: the bar's columns (default: description, bar, done/total, elapsed).
        shown: False hides it on a terminal too (``--quiet``, or plain lines instead).
    """
    bar = Progress(
        *(
            columns
            or (
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
            )
        ),
        console=err_console,
        transient=False,
        disable=not (shown and err_console.is_terminal),
    )
    with bar:
        try:
            yield bar
        except BaseException:
            bar.live.transient = True
            raise


def print_rows(title: str, rows: list[dict[str, object]]) -> None:
    """Print a list of uniform dicts as a rich table."""
    table = Table(title=escape(title))
    if not rows:
        console.print(f"{title}: nothing to show")
        return
    for key in rows[0]:
        table.add_column(str(key), justify="right")
    for row in rows:
        table.add_row(*(f"{v:.4f}" if isinstance(v, float) else str(v) for v in row.values()))
    console.print(table)

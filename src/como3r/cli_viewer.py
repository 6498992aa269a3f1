"""``--viewer`` of ``como3r run`` and ``como3r demo`` (manual: docs/viewer.md).

``--viewer spawn``, ``--viewer serve`` or ``--viewer save FILE.rrd``: the option's value
is one word except after ``save``, so :class:`ViewerCommand` joins ``save FILE`` into
``save=FILE`` before click parses the command line. Everything else lives in
:mod:`como3r.viewer`, which imports rerun only when a viewer opens.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path

from como3r.cli_common import Command, err_console
from como3r.live import LiveCallback
from como3r.viewer import ViewerSpec, check_viewer, open_viewer

#: help texts are rich markup: the escaped bracket keeps `[viewer]` from being read as a tag
VIEWER_HELP = (
    'Live 3D viewer (needs: pip install "como3r\\[viewer]"): spawn (open rerun\'s '
    "viewer), serve (for a viewer on another machine; prints the URL) or save "
    "FILE.rrd (a recording to open with `rerun FILE.rrd`)."
)


def join_save_file(args: list[str]) -> list[str]:
    """``[..., "--viewer", "save", FILE, ...]`` as ``[..., "--viewer", "save=FILE", ...]``
    (also after ``--viewer=save``); other arguments as they are."""
    joined: list[str] = []
    i = 0
    while i < len(args):
        if args[i] == "--viewer=save":
            joined.append("--viewer")
        elif not (args[i] == "save" and joined[-1:] == ["--viewer"]):
            joined.append(args[i])
            i += 1
            continue
        following = args[i + 1] if i + 1 < len(args) else None
        if following is None or following.startswith("-"):
            joined.append("save")  # no file: parse_viewer says what is missing
            i += 1
        else:
            joined.append(f"save={following}")
            i += 2
    return joined


class ViewerCommand(Command):
    """A command with ``--viewer save FILE`` (two words) among its options."""

    def parse_args(self, ctx, args):  # type: ignore[no-untyped-def]
        return super().parse_args(ctx, join_save_file(list(args)))


def check_viewer_option(viewer: str | None, out: Path) -> ViewerSpec | None:
    """The checked ``--viewer`` (None without one), before any work.

    Raises:
        InputError: a bad value, or rerun not installed (one line naming the extra).
    """
    return None if viewer is None else check_viewer(viewer, out)


@contextlib.contextmanager
def live_viewer(spec: ViewerSpec | None) -> Iterator[LiveCallback | None]:
    """The live-event sink of ``spec`` (None without a viewer) for the block. ``serve``
    prints where to connect; when the block succeeds it keeps serving until Ctrl-C, so a
    viewer can still connect to a finished run."""
    if spec is None:
        yield None
        return
    viewer = open_viewer(spec)
    try:
        if viewer.urls is not None:
            grpc, web = viewer.urls
            _say(
                f"viewer: serving the run; connect with `rerun {grpc}` or a browser at {web} "
                "(localhost: this machine; from another, its address or an SSH tunnel of "
                "both ports)"
            )
        yield viewer
        if viewer.urls is not None:
            _say("viewer: the run is done; still serving the recording (Ctrl-C to stop)")
            with contextlib.suppress(KeyboardInterrupt):
                while True:
                    time.sleep(1.0)
    finally:
        viewer.close()
    if spec.path is not None:
        _say(f"viewer: wrote {spec.path}")


def _say(line: str) -> None:
    err_console.print(line, markup=False, highlight=False, soft_wrap=True)

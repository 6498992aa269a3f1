"""What ``--viewer`` asks for (:class:`ViewerSpec`): the modes, and the file of ``save``.

Both :mod:`como3r.viewer` (which parses and checks the option) and
:mod:`como3r.viewer.recording` (which opens the recording) use it; it imports neither.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: what ``--viewer`` accepts: open the native viewer, serve for a remote one, write a file
MODES = ("spawn", "serve", "save")


@dataclass(frozen=True)
class ViewerSpec:
    """Where the live events go.

    Attributes:
        mode: one of :data:`MODES`.
        path: the ``.rrd`` file of ``save`` (None otherwise).
    """

    mode: str
    path: Path | None = None

"""Opening an agent's input: :func:`open_agent` opens and validates any supported input (an
agent folder or video, a dataset sequence folder, a ROS log; :mod:`como3r.data.readers`
detects the layout) as an :class:`~como3r.data.agent_input.AgentInput`, and
:func:`quiet_reading` opens one again without repeating the readers' warnings.

:func:`open_agent` does every cheap check up front (existence, counts, all text files, image
and map headers), so a bad input fails before any SLAM work starts; pixels are decoded lazily
by :meth:`AgentInput.load_frame` and :meth:`AgentInput.frames`, which check them in turn.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

from como3r.data.agent_input import AgentInput
from como3r.data.readers import open_input


def open_agent(
    path: str | Path, fps: float = 30.0, format: str = "auto", topic: str = ""
) -> AgentInput:
    """Open and validate an input: an agent folder or video, a dataset sequence folder
    (TUM RGB-D, 7-Scenes, EuRoC MAV, KITTI odometry, Tanks and Temples) or a ROS log
    (:mod:`como3r.data.readers`).

    Args:
        path: agent folder, video file, dataset sequence folder, ``.bag`` file or ROS 2 bag
            folder.
        fps: frame rate for default timestamps (``index / fps``; 7-Scenes and Tanks and
            Temples: frame number / fps). A video without ``timestamps.txt`` uses its own frame
            rate when the container reports one.
        format: ``auto`` (detect from the folder's layout) or one of
            :data:`como3r.data.readers.FORMATS`.
        topic: a ROS log's image topic (:mod:`como3r.data.readers.rosbag`); empty: its
            only one. Refused for other inputs.

    Raises:
        InputError: naming the offending file, for any missing, empty, unreadable or
            inconsistent part of the input, a folder of no known layout, a ``format``
            the folder does not match, or a ``topic`` that is not a ROS log's image topic.
    """
    return open_input(path, fps=fps, format=format, topic=topic)


@contextlib.contextmanager
def quiet_reading() -> Iterator[None]:
    """Open inputs without the readers' warnings (frames left out, ...): for a second
    opening of an input whose first opening in the run says them (the command line's check,
    an agent process), so each is said once."""
    data_logger = logging.getLogger("como3r.data")
    level = data_logger.level
    data_logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        data_logger.setLevel(level)

"""A robot's declaration of what its odometry comes from: ``odometry.json`` beside
``odometry.txt``, read and written (what it means to the pose graph:
:mod:`como3r.decentralized.odometry_kind`).

.. code-block:: json

    {"kind": "vio"}
    {"kind": "vio", "start_scale_error": 0.2, "start_depths": 0.5}
    {"kind": "metric"}

``start_scale_error`` (a fraction, >= 0; 0: its start has converged, no discount) and
``start_depths`` (> 0) apply to ``vio`` only. The input layer reads the file so that
:func:`~como3r.data.split.split_sequence` can hand each piece of a split its own
declaration; the decentralized mode reads it through here too.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from como3r.data.agent_input import AgentInput
from como3r.errors import InputError

ODOMETRY_KIND_FILE = "odometry.json"
KINDS = ("vio", "metric")
"""Declarable odometry kinds (:mod:`como3r.decentralized.odometry_kind`)."""

_KEYS = ("kind", "start_scale_error", "start_depths")


@dataclass(frozen=True)
class OdometryKind:
    """A robot's declared odometry (:mod:`como3r.decentralized.odometry_kind`).

    Attributes:
        kind: one of :data:`KINDS`.
        start_scale_error: ``vio``: the start's scale error (fraction, >= 0); None: the
            configuration's ``vio_start_scale_error``.
        start_depths: ``vio``: its decay length in scene depths (> 0); None: the
            configuration's ``vio_start_depths``.
    """

    kind: str
    start_scale_error: float | None = None
    start_depths: float | None = None


def declaration_folder(agent: AgentInput) -> Path:
    """The folder holding an input's ``odometry.txt`` (and its declaration)."""
    return agent.root if agent.root.is_dir() else agent.root.parent


def read_odometry_kind(folder: str | Path) -> OdometryKind | None:
    """The declaration ``folder/odometry.json``; None when there is none (undeclared).

    Raises:
        InputError: naming the file, when it is not a JSON object of :data:`KINDS`'
            ``kind`` with optional finite ``start_scale_error >= 0`` and
            ``start_depths > 0`` (``vio`` only), or has other keys.
    """
    path = Path(folder) / ODOMETRY_KIND_FILE
    if not path.is_file():
        return None
    try:
        document = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not readable JSON ({exc})") from None
    if not isinstance(document, dict):
        raise InputError(f'{path}: must be a JSON object such as {{"kind": "vio"}}')
    unknown = sorted(set(document) - set(_KEYS))
    if unknown:
        raise InputError(f"{path}: unknown key(s) {unknown} (valid: {', '.join(_KEYS)})")
    kind = document.get("kind")
    if kind not in KINDS:
        raise InputError(
            f'{path}: "kind" must be one of {", ".join(KINDS)} (LiDAR-inertial, stereo or '
            f"wheel odometry is metric), got {kind!r}"
        )
    values: dict[str, float] = {}
    for key, low, strict in (("start_scale_error", 0.0, False), ("start_depths", 0.0, True)):
        if key not in document:
            continue
        value = document[key]
        if kind != "vio":
            raise InputError(f"{path}: {key!r} applies to kind vio only, not {kind!r}")
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not number or not math.isfinite(value) or value < low or (strict and value == low):
            bound = "> 0" if strict else ">= 0"
            raise InputError(f"{path}: {key!r} must be a finite number {bound}, got {value!r}")
        values[key] = float(value)
    return OdometryKind(kind, **values)


def write_odometry_kind(folder: str | Path, declared: OdometryKind) -> Path:
    """Write ``folder/odometry.json`` (the keys that are set); returns its path."""
    document: dict[str, str | float] = {"kind": declared.kind}
    if declared.start_scale_error is not None:
        document["start_scale_error"] = declared.start_scale_error
    if declared.start_depths is not None:
        document["start_depths"] = declared.start_depths
    path = Path(folder) / ODOMETRY_KIND_FILE
    path.write_text(json.dumps(document) + "\n")
    return path

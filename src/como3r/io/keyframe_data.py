"""Keyframe contents of a run folder: what the exports (:mod:`como3r.io.export`) read.

A run writes, next to ``keyframes/agent_<a>.txt``, one folder per agent with two files per
keyframe, named by its keyframe id ``k`` (``graph.json``'s ``"keyframe"``)::

    keyframes/agent_<a>/<k:06d>.c3z   X (H, W, 3) float32  canonical pointmap, own camera frame
                                      C (H, W) float32     confidence per contributing frame
                                      K (3, 3) float64     intrinsics at (H, W); absent when
                                                           the run had none (uncalibrated
                                                           without self-calibration)
    keyframes/agent_<a>/<k:06d>.png   (H, W, 3) RGB        the keyframe's image at that size

The arrays are compressed losslessly (:mod:`como3r.io.packed_arrays`: 1.7 MB of the 3.1 MB a
512x384 keyframe of the demo scene took as ``.npz``, the pointmap's noise being what is left);
run folders written before hold the same arrays as ``<k:06d>.npz``, which is read as well.

``X`` is in the keyframe's camera frame *before* its pose's scale: with ``T_WC = (t, q, s)``
from ``graph.json`` a pixel's world point is ``s R(q) X + t`` (as ``map.ply`` is made), its
depth in world units ``s X_z``. Pixel centres are at integer coordinates (``K``'s convention,
:mod:`como3r.geometry.camera`).
"""

from __future__ import annotations

import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from como3r.errors import InputError
from como3r.io.packed_arrays import SUFFIX, read_packed, write_packed

#: the arrays' file of run folders written before they were compressed
OLD_SUFFIX = ".npz"


def keyframe_data_path(run: str | Path, agent: int, kf_id: int, suffix: str) -> Path:
    """``run/keyframes/agent_<agent>/<kf_id:06d><suffix>`` (``suffix``: ``.c3z``, ``.npz``
    or ``.png``)."""
    return Path(run) / "keyframes" / f"agent_{agent}" / f"{kf_id:06d}{suffix}"


def keyframe_arrays_path(run: str | Path, agent: int, kf_id: int) -> Path:
    """The file holding a keyframe's arrays: ``<kf_id:06d>.c3z``, or ``.npz`` in a run folder
    written before, where only that one exists."""
    packed = keyframe_data_path(run, agent, kf_id, SUFFIX)
    old = packed.with_suffix(OLD_SUFFIX)
    return old if not packed.is_file() and old.is_file() else packed


def write_keyframe_data(out: str | Path, agents: Sequence[Any]) -> None:
    """Write every keyframe's pointmap, confidence, intrinsics and image.

    Args:
        out: the run folder being written.
        agents: front-ends or agent results (``agent``, ``keyframes`` with ``kf_id``,
            ``X_hat (H, W, 3)``, ``mean_confidence() (H, W)``, ``K (3, 3)`` or None and
            ``colors (H, W, 3)`` uint8).
    """
    for agent in agents:
        for kf in agent.keyframes:
            packed = keyframe_data_path(out, agent.agent, kf.kf_id, SUFFIX)
            packed.parent.mkdir(parents=True, exist_ok=True)
            arrays = {
                "X": kf.X_hat.detach().cpu().numpy().astype(np.float32),
                "C": kf.mean_confidence().detach().cpu().numpy().astype(np.float32),
            }
            if kf.K is not None:
                arrays["K"] = kf.K.detach().cpu().numpy().astype(np.float64)
            write_packed(packed, arrays)
            Image.fromarray(np.asarray(kf.colors, dtype=np.uint8)).save(
                packed.with_suffix(".png"), compress_level=1
            )


@dataclass(frozen=True)
class KeyframeData:
    """One keyframe's contents (see the module docstring for frames and units).

    Attributes:
        X: ``(H, W, 3)`` float32 pointmap in the keyframe's camera, before the pose's scale.
        C: ``(H, W)`` float32 confidence.
        K: ``(3, 3)`` float64 intrinsics, or None.
        image_path: the keyframe's ``(H, W)`` RGB PNG.
        arrays_path: the file the arrays came from (``.c3z``, or ``.npz`` in an older run
            folder); None: the ``.c3z`` beside the image.
    """

    X: np.ndarray
    C: np.ndarray
    K: np.ndarray | None
    image_path: Path
    arrays_path: Path | None = None

    @property
    def source(self) -> Path:
        """The file to name in an error about the arrays."""
        return self.arrays_path or self.image_path.with_suffix(SUFFIX)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return int(self.X.shape[0]), int(self.X.shape[1])

    def image(self) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB.

        Raises:
            InputError: the PNG is unreadable or not of the pointmap's size.
        """
        try:
            with Image.open(self.image_path) as image:
                rgb = np.asarray(image.convert("RGB"))
        except (OSError, UnidentifiedImageError) as exc:
            raise InputError(f"{self.image_path}: cannot read keyframe image ({exc})") from None
        if rgb.shape[:2] != self.shape:
            raise InputError(
                f"{self.image_path}: image is {rgb.shape[1]}x{rgb.shape[0]}, its "
                f"pointmap {self.shape[1]}x{self.shape[0]}"
            )
        return rgb


def read_keyframe_data(run: str | Path, agent: int, kf_id: int) -> KeyframeData:
    """Read one keyframe's files written by :func:`write_keyframe_data`.

    Raises:
        InputError: a file is missing or malformed (naming it).
    """
    arrays_path = keyframe_arrays_path(run, agent, kf_id)
    png = arrays_path.with_suffix(".png")
    for path in (arrays_path, png):
        if not path.is_file():
            raise InputError(
                f"{path}: missing keyframe data (a run folder written before "
                f"como3r export existed has none: run the input again)"
            )
    X, C, K = _read_arrays(arrays_path)
    H, W = X.shape[:2]
    if X.shape != (H, W, 3) or C.shape != (H, W) or (K is not None and K.shape != (3, 3)):
        raise InputError(
            f"{arrays_path}: arrays of shapes X {X.shape}, C {C.shape}"
            f"{'' if K is None else f', K {K.shape}'} are not (H, W, 3), (H, W), "
            f"(3, 3)"
        )
    return KeyframeData(
        X=X.astype(np.float32),
        C=C.astype(np.float32),
        K=None if K is None else K.astype(np.float64),
        image_path=png,
        arrays_path=arrays_path,
    )


def _read_arrays(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``X``, ``C`` and ``K`` (or None) of a keyframe's ``.c3z`` or (older) ``.npz`` file."""
    try:
        if path.suffix == SUFFIX:
            data = read_packed(path)
            return data["X"], data["C"], data.get("K")
        with np.load(path, allow_pickle=False) as npz:
            return npz["X"], npz["C"], npz["K"] if "K" in npz.files else None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: not a keyframe data file ({exc})") from None

"""What several dataset readers share: text files' data lines, rigid transforms as datasets publish them (matrices of
printed numbers: 7-Scenes pose files, KITTI ``poses/XX.txt``, EuRoC ``T_BS``) checked and
turned into como3r poses, numbers parsed with the file and line in the message, and folders
of images named by frame number (KITTI ``image_2/`` or ``image_0/``, Tanks and Temples ``image/``)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from como3r.data.agent_input import IMAGE_SUFFIXES
from como3r.errors import InputError
from como3r.geometry.lie import matrix_to_quat

#: largest |R^T R - I| entry and |last row - (0, 0, 0, 1)| of an accepted matrix
RIGID_TOLERANCE = 1e-3


def rigid_poses(
    matrices: np.ndarray, sources: Sequence[str | Path], what: str = "camera-to-world"
) -> torch.Tensor:
    """``(N, 8)`` float64 poses (t, q_xyzw, s = 1) of rigid transform matrices.

    Args:
        matrices: ``(N, 4, 4)`` or ``(N, 3, 4)`` (last row ``0 0 0 1`` implied) float64.
        sources: ``(N,)`` where each matrix was read (a file, or ``file:line``), for the
            message.
        what: what the transforms are, for the message (``camera-to-world``, ...).

    Raises:
        InputError: a matrix that is not a rotation and a translation (to
            :data:`RIGID_TOLERANCE`), naming its source.
    """
    R = matrices[:, :3, :3]
    error = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    if matrices.shape[1] == 4:
        error = np.maximum(error, np.abs(matrices[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1))
    bad = np.flatnonzero((error > RIGID_TOLERANCE) | (np.linalg.det(R) <= 0))
    if bad.size:
        raise InputError(
            f"{sources[bad[0]]}: not a rigid {what} transform (a rotation "
            f"and a translation, last row 0 0 0 1; off by {error[bad[0]]:.2g})"
        )
    q = matrix_to_quat(torch.from_numpy(np.ascontiguousarray(R)))
    t = torch.from_numpy(np.ascontiguousarray(matrices[:, :3, 3]))
    return torch.cat([t, q, torch.ones(len(matrices), 1, dtype=torch.float64)], dim=1)


def data_lines(path: Path, what: str) -> list[tuple[int, str]]:
    """``(line number, text)`` of the lines of a text file that hold data: ``#`` starts a
    comment, blank lines are skipped.

    Raises:
        InputError: a missing or unreadable file, or one without data lines, saying it is
            ``what`` (``"times of the KITTI sequence"``, ...).
    """
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise InputError(f"{path}: missing ({what})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read {what} ({exc})") from None
    data = [(n, text) for n, line in enumerate(lines, 1) if (text := line.split("#", 1)[0].strip())]
    if not data:
        raise InputError(f"{path}: empty ({what})")
    return data


def parse_numbers(tokens: Sequence[str], count: int, where: str, what: str) -> np.ndarray:
    """``(count,)`` float64 of text tokens.

    Raises:
        InputError: ``where: expected <count> finite numbers (<what>), ...`` for another
            count, a token that is not a number, or a non-finite one.
    """
    try:
        values = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        raise InputError(
            f"{where}: expected {count} numbers ({what}), found text that is not a number"
        ) from None
    if values.size != count or not np.isfinite(values).all():
        raise InputError(f"{where}: expected {count} finite numbers ({what}), got {values.size}")
    return values


def numbered_images(
    folder: Path, number: re.Pattern[str], example: str
) -> tuple[tuple[Path, ...], np.ndarray]:
    """The images of ``folder`` in frame-number order, and their ``(N,)`` int64 numbers.

    Args:
        folder: the image folder.
        number: a pattern whose ``fullmatch`` of an image's stem has the frame number as its
            first group.
        example: a conforming stem, for the message.

    Raises:
        InputError: no images, a name without a frame number, or two images of one number.
    """
    found: dict[int, Path] = {}
    for image in sorted(folder.iterdir()):
        if not (image.is_file() and image.suffix.lower() in IMAGE_SUFFIXES):
            continue
        match = number.fullmatch(image.stem)
        if match is None:
            raise InputError(
                f"{image}: not named by its frame number (expected e.g. {example}{image.suffix})"
            )
        frame = int(match.group(1))
        if frame in found:
            raise InputError(f"{image}: frame {frame} has two images (also {found[frame].name})")
        found[frame] = image
    if not found:
        raise InputError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    numbers = sorted(found)
    return tuple(found[n] for n in numbers), np.array(numbers, dtype=np.int64)

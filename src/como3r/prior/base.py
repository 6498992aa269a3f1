"""The prior interface (manual: docs/api/index.md; C-Sec. 3.2).

Everything above ``prior/`` depends on this module alone, so the MASt3R network and the
simulated sensor are interchangeable. A prior turns views into geometry:

* ``encode(view) -> Encoding``: per-image work done once.
* ``decode(enc_i, enc_j) -> PairPrediction``: both pointmaps in camera i's frame.
* ``decode_pairs(pairs)``: many ordered pairs (i, j) at once.
* ``decode_symmetric(pairs)``: (i, j) and (j, i) of many pairs at once.
* ``retrieval_features(enc) -> (descriptors, attention)``: what ASMK indexes.
* ``can_reencode(agent)``: whether ``encode`` of a keyframe's uint8 colours
  (:func:`view_from_colors`) gives that agent's encoding again, so a receiver that says so
  needs no encoding sent or stored ("what can be recomputed from the input is not stored
  twice").
* ``encode_from_record(view, record)``: the encoding again from a keyframe's colours and the
  :class:`EncodingRecord` that travelled and was stored in its place
  (:meth:`Encoding.portable`: what a prior needs beside the image, e.g. the simulated
  prior's ground truth).
* ``encode_again(colors, agent, index, record)``: whichever of the two a keyframe needs, the
  one place a receiver (a coordinator, a robot) remakes an encoding.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from como3r.errors import PriorError


@dataclass(frozen=True)
class View:
    """One pre-processed frame as handed to a prior.

    It carries no ground truth: the simulated prior looks its own up by ``(agent, index)``
    (:mod:`como3r.prior.ground_truth`).

    Attributes:
        image: ``(3, H, W)`` float32 RGB in [-1, 1] (MAST3R_SPEC.md §2 normalisation).
        agent: agent id the frame belongs to.
        index: frame index within the agent's stream.
        K: ``(3, 3)`` the user's intrinsics at the resolution of ``image``, in calibrated
            runs only (``--calib``); None otherwise.
    """

    image: Tensor
    agent: int = 0
    index: int = 0
    K: Tensor | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the image."""
        return int(self.image.shape[-2]), int(self.image.shape[-1])


def view_from_colors(colors: np.ndarray, agent: int, index: int) -> View:
    """The view whose image a keyframe's colours are: ``(H, W, 3)`` uint8 -> ``(3, H, W)``
    float32 ``2 * v / 255 - 1``, computed as ``(v / 255 - 0.5) / 0.5`` exactly as
    :meth:`como3r.data.preprocess.Preprocessor.to_network` made the image the agent encoded
    (bit-identical), without intrinsics (no prior's encoding reads ``View.K``).
    """
    # a copy: decoded colours may be a read-only view of the message's bytes
    pixels = torch.from_numpy(np.array(colors, dtype=np.uint8)).permute(2, 0, 1)
    return View(image=(pixels.to(torch.float32) / 255.0 - 0.5) / 0.5, agent=agent, index=index)


@dataclass(frozen=True)
class Encoding:
    """Per-image work of a prior, computed once per view.

    Concrete priors subclass it and add their own fields (MASt3R: encoder tokens).

    Attributes:
        agent: agent id of the encoded view.
        index: frame index of the encoded view.
        shape: ``(H, W)`` of the encoded image.
    """

    agent: int
    index: int
    shape: tuple[int, int]

    def portable(self) -> Encoding:
        """What travels to a coordinator and is stored in place of this encoding: itself,
        or an :class:`EncodingRecord` from which the prior makes it again
        (:meth:`Prior.encode_from_record`) when that is smaller."""
        return self

    def for_decoding(self) -> Encoding:
        """This encoding as a receiver that only decodes it needs it: without what only
        making it again needs (the record :meth:`portable` gives)."""
        return self


@dataclass(frozen=True)
class EncodingRecord(Encoding):
    """What a prior needs, besides the image, to make a view's encoding again
    (:meth:`Prior.encode_from_record`): it travels and is stored in the encoding's place.
    It is no encoding: a prior decodes none (a coordinator's
    :class:`~como3r.coordination.encodings.KeyframeEncodings` makes the encoding first)."""


@dataclass(frozen=True)
class PairPrediction:
    """Output of decoding the ordered pair (i, j), everything in camera i's frame.

    Shapes are ``(H, W, ...)`` for one pair; a batch of pairs prepends ``B``.

    Attributes:
        X_ii: ``(H, W, 3)`` pointmap of view i in camera i.
        X_ji: ``(H, W, 3)`` pointmap of view j in camera i.
        C_ii: ``(H, W)`` confidence of ``X_ii``, >= 1.
        C_ji: ``(H, W)`` confidence of ``X_ji``, >= 1.
        D_ii: ``(H, W, d)`` unit-norm local descriptors of view i.
        D_ji: ``(H, W, d)`` unit-norm local descriptors of view j.
        Q_ii: ``(H, W)`` descriptor confidence of view i, > 0.
        Q_ji: ``(H, W)`` descriptor confidence of view j, > 0.
    """

    X_ii: Tensor
    X_ji: Tensor
    C_ii: Tensor
    C_ji: Tensor
    D_ii: Tensor
    D_ji: Tensor
    Q_ii: Tensor
    Q_ji: Tensor

    def to(self, device: torch.device | str) -> PairPrediction:
        """Copy of the prediction with every tensor on ``device``."""
        return PairPrediction(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})

    def unbatch(self) -> list[PairPrediction]:
        """Split a batched prediction ``(B, H, W, ...)`` into B single predictions."""
        batch = self.X_ii.shape[0]
        return [
            PairPrediction(**{f.name: getattr(self, f.name)[b] for f in fields(self)})
            for b in range(batch)
        ]


class Prior(abc.ABC):
    """A learned (or simulated) two-view 3D prior."""

    #: dimension ``d`` of the local descriptors in ``PairPrediction.D_*``
    descriptor_dim: int = 24

    @abc.abstractmethod
    def encode(self, view: View) -> Encoding:
        """Per-image work for ``view``; cache the result, it is reused by every pair."""

    @abc.abstractmethod
    def decode(self, enc_i: Encoding, enc_j: Encoding) -> PairPrediction:
        """Predict the ordered pair (i, j): pointmaps of both views in camera i."""

    def decode_pairs(self, pairs: Sequence[tuple[Encoding, Encoding]]) -> list[PairPrediction]:
        """Decode every ordered pair (i, j); priors override this to batch."""
        return [self.decode(a, b) for a, b in pairs]

    def decode_symmetric(
        self, pairs: Sequence[tuple[Encoding, Encoding]]
    ) -> list[tuple[PairPrediction, PairPrediction]]:
        """Decode (i, j) and (j, i) for every pair; priors override this to batch."""
        return [(self.decode(a, b), self.decode(b, a)) for a, b in pairs]

    @abc.abstractmethod
    def retrieval_features(self, enc: Encoding) -> tuple[Tensor, Tensor]:
        """Local retrieval descriptors ``(N, d_r)`` and their attention ``(N,)``."""

    def can_reencode(self, agent: int) -> bool:
        """Whether any coordinator with this prior (this session's, or a later one: a
        resume, a saved map, a merge) remakes ``agent``'s encodings from their keyframes'
        colours: ``encode(view_from_colors(colors, agent, frame_index))`` equals the
        encoding the agent made (same network and settings). Such a coordinator is sent no
        encodings and stores none (:mod:`como3r.coordination.encodings`); the default is
        no."""
        return False

    def encode_from_record(self, view: View, record: EncodingRecord) -> Encoding:
        """The encoding of ``view`` (a keyframe's colours, :func:`view_from_colors`) made
        with what ``record`` holds (:meth:`Encoding.portable`), bit-identical to the one the
        agent made.

        Raises:
            PriorError: this prior makes no encodings from records (the default), or not
                from this one.
        """
        raise PriorError(
            f"{type(self).__name__} cannot encode agent {view.agent}'s frame {view.index} "
            f"from a {type(record).__name__} (another prior made it)"
        )

    def encode_again(
        self, colors: np.ndarray, agent: int, index: int, record: EncodingRecord | None = None
    ) -> Encoding:
        """The encoding of a keyframe's ``(H, W, 3)`` uint8 ``colors`` (``agent``'s frame
        ``index``) as its agent made it: :meth:`encode` of them where the prior remakes
        encodings from the image alone (:meth:`can_reencode`), else
        :meth:`encode_from_record` with ``record``, under the record's own agent and frame
        (a merge renumbers agents, a robot numbers its keyframes, not their frames).

        Raises:
            PriorError: the prior makes no encoding from ``record``.
        """
        if record is None:
            return self.encode(view_from_colors(colors, agent, index))
        return self.encode_from_record(view_from_colors(colors, record.agent, record.index), record)

    def describe(self) -> dict[str, object]:
        """Parameters of the prior, reported with every result it produces."""
        return {"name": type(self).__name__}

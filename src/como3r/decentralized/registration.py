"""Two-stage registration of keyframe pairs with the prior (F-Sec. III-B, F-Fig. 1, F-Fig. 4).

Each robot encodes its own keyframes once (:meth:`Registrar.own_encoding`); for a loop
candidate (I_i^alpha, I_j^beta) the encoding of I_j^beta travels to robot alpha, which
decodes the pair (where the prior can encode an image again, as MASt3R can, the image's
colours travel instead and robot alpha encodes them: 0.2 MB of lossless WebP at 512x384
against 1.25 MB of float16 tokens; :meth:`Registrar.reply_for_peer`), matches the two views' descriptors (reciprocal nearest neighbours,
:func:`~.matching.reciprocal_matches`) and estimates the relative pose robustly from the matched
3-D points (:func:`ransac_similarity`: minimal 3-point similarities, then Umeyama on the
inliers; a pose explaining fewer than :func:`required_inliers` of the matches is a failed
registration, a test relative to the number of matches so that it holds at any image size).
The pose of a registered pair is then fitted to the two decodes' pointmaps of every pixel
(:func:`~.dense_fit.dense_similarity`, ``registration.pose_fit``: ``dense``), or kept from
the matches' consensus (``matches``).
Encodings are cached, so a keyframe in several candidates is encoded (and sent)
once; :class:`RegistrationStats` counts what a naive pipeline that encodes both images of
every pair would have encoded.

The relative pose ``T_ij`` maps points of camera j into camera i; its translation is in the
units of view i's pointmap (the prior's scale, resolved later by F-Eq. 6-8).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor

from como3r.config_decentralized import RegistrationConfig
from como3r.decentralized.dense_fit import (
    camera_shift,
    dense_similarity,
    front_depths,
    points_shift,
)
from como3r.decentralized.matching import reciprocal_matches
from como3r.errors import GeometryError, PriorError
from como3r.geometry.lie import matrix_to_quat, sim3_act
from como3r.geometry.umeyama import umeyama_sim3, umeyama_sim3_batched
from como3r.prior.base import (
    Encoding,
    EncodingRecord,
    PairPrediction,
    Prior,
    View,
)
from como3r.prior.simulated_keys import generator

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Registration:
    """Result of registering the ordered pair (i, j).

    Attributes:
        correspondences: number of reciprocal descriptor matches (F-Eq. 1's counts).
        inliers: matches consistent with ``T_ij``.
        T_ij: ``(8,)`` float64 similarity mapping camera-j points into camera i (t, q_xyzw,
            s), or None when no pose could be estimated.
    """

    correspondences: int
    inliers: int
    T_ij: Tensor | None


@dataclass
class RegistrationStats:
    """Work done by one robot's registrar (F-Fig. 4).

    Attributes:
        encodes: images encoded (each keyframe at most once; place descriptors included).
        encode_seconds: time spent encoding.
        decodes: pairs decoded (both directions count as one symmetric decode).
        decode_seconds: time spent in the prior's decoder.
        match_seconds: time spent matching the decoded pairs' descriptors.
        fit_seconds: time spent fitting their relative poses (RANSAC).
        naive_encodes: encodes of a pipeline that encodes both images of every decoded pair.
        registration_encodes: this robot's keyframes whose encoding some decode used (here or
            at another robot): what the two-stage scheme encodes for registration.
        foreign_encodes: other robots' keyframes encoded here from the colours they sent
            (their time is in ``encode_seconds``).
        dense_fits_refused: registered pairs whose dense fit was too far from the matches'
            consensus (``registration.dense_max_shift_ratio``), so the consensus's was kept.
        dense_fits_refused_points: of these, the ones whose camera j was within the bar
            (:func:`camera_shift`) but view j's points were not (:func:`points_shift`): a fit
            turned about camera i.
    """

    encodes: int = 0
    encode_seconds: float = 0.0
    decodes: int = 0
    decode_seconds: float = 0.0
    match_seconds: float = 0.0
    fit_seconds: float = 0.0
    naive_encodes: int = 0
    registration_encodes: int = 0
    foreign_encodes: int = 0
    dense_fits_refused: int = 0
    dense_fits_refused_points: int = 0

    def to_json(self) -> dict[str, float]:
        return {
            "encodes": self.encodes,
            "encode_seconds": self.encode_seconds,
            "decodes": self.decodes,
            "decode_seconds": self.decode_seconds,
            "match_seconds": self.match_seconds,
            "fit_seconds": self.fit_seconds,
            "naive_encodes": self.naive_encodes,
            "registration_encodes": self.registration_encodes,
            "foreign_encodes": self.foreign_encodes,
            "dense_fits_refused": self.dense_fits_refused,
            "dense_fits_refused_points": self.dense_fits_refused_points,
        }


def ransac_similarity(
    src: Tensor, dst: Tensor, config: RegistrationConfig, gen: torch.Generator
) -> tuple[Tensor, Tensor] | None:
    """Robust similarity ``dst ~= s R src + t`` from putative 3-D correspondences.

    Args:
        src: ``(M, 3)`` points (camera j).
        dst: ``(M, 3)`` matched points (camera i).
        config: hypotheses, inlier ratio and minimum inliers.
        gen: random generator of the minimal samples.

    Returns:
        ``T (8,)`` float64 and the ``(M,)`` bool inlier mask, or None when fewer than
        :func:`required_inliers` correspondences support the best hypothesis.
    """
    count = src.shape[0]
    needed = required_inliers(count, config)
    if count < max(3, needed):
        return None
    src, dst = src.double(), dst.double()
    threshold = config.ransac_inlier_ratio * dst.norm(dim=-1)
    samples = torch.stack(
        [torch.randperm(count, generator=gen)[:3] for _ in range(config.ransac_hypotheses)]
    )
    # closed-form similarities of the minimal samples, scored as matrices (B, M, 3)
    R, t, s = umeyama_sim3_batched(src[samples], dst[samples])
    moved = s[:, None, None] * torch.matmul(src[None], R.transpose(1, 2)) + t[:, None]
    support = ((moved - dst[None]).norm(dim=-1) < threshold).sum(dim=1)
    k = int(torch.argmax(support))
    best = torch.cat([t[k], matrix_to_quat(R[k]), s[k : k + 1]])
    inliers = (sim3_act(best, src) - dst).norm(dim=-1) < threshold
    for _ in range(2):
        # the floor only: the fraction judges the refined fit, which may gain support
        if int(inliers.sum()) < config.min_inliers:
            return None
        try:
            refined = umeyama_sim3(src[inliers], dst[inliers])
        except GeometryError:
            return None
        refined_inliers = (sim3_act(refined, src) - dst).norm(dim=-1) < threshold
        if int(refined_inliers.sum()) < int(inliers.sum()):
            break
        best, inliers = refined, refined_inliers
    if int(inliers.sum()) < needed:
        return None
    return best, inliers


def required_inliers(count: int, config: RegistrationConfig) -> int:
    """Inliers a fit of ``count`` putative correspondences needs: ``min_inliers``, and
    ``min_inlier_fraction`` of ``count`` (chance support grows with the number of matches,
    hence with the image size; the fraction keeps the test resolution-free)."""
    return max(config.min_inliers, math.ceil(config.min_inlier_fraction * count))


def register_predictions(
    pred_ij: PairPrediction,
    pred_ji: PairPrediction,
    config: RegistrationConfig,
    gen: torch.Generator,
    stats: RegistrationStats | None = None,
) -> Registration:
    """Match a decoded pair, test the matches' consensus and estimate the relative pose
    (module docstring). A dense fit that fails (degenerate pointmaps) fails the registration.

    Args:
        pred_ij: decode of (i, j): ``X_ii``, descriptors ``D_ii`` (view i) and ``D_ji``
            (view j) of one decoder pass.
        pred_ji: decode of (j, i): ``X_ii`` is view j's pointmap in camera j.
        config: registration parameters.
        gen: RANSAC generator.
        stats: when given, the matching and fitting seconds are added to it.
    """
    start = time.perf_counter()
    p_i, p_j = reciprocal_matches(pred_ij.D_ii, pred_ij.D_ji, pred_ij.Q_ii, pred_ij.Q_ji, config)
    matched = time.perf_counter()
    dst = pred_ij.X_ii.reshape(-1, 3)[p_i]
    src = pred_ji.X_ii.reshape(-1, 3)[p_j]
    fit = ransac_similarity(src, dst, config, gen)
    if stats is not None:
        stats.match_seconds += matched - start
        stats.fit_seconds += time.perf_counter() - matched
    if fit is None:
        return Registration(int(p_i.numel()), 0, None)
    T, inliers = fit
    if config.pose_fit == "dense":
        try:
            dense = dense_similarity(pred_ij, pred_ji)
        except GeometryError:
            return Registration(int(p_i.numel()), 0, None)
        # the camera alone misses a fit turned about camera i, the points alone one turned
        # about the scene (its points stay near where they were, the camera moves)
        shift = camera_shift(T, dense, pred_ij.X_ii)
        points = points_shift(T, dense, pred_ji.X_ii)
        if max(shift, points) <= config.dense_max_shift_ratio:
            T = dense
        else:
            logger.debug(
                "registration: dense fit's camera %.2f depths off, points %.2f of their "
                "range; consensus's pose kept",
                shift,
                points,
            )
            if stats is not None:
                stats.dense_fits_refused += 1
                stats.dense_fits_refused_points += int(shift <= config.dense_max_shift_ratio)
    return Registration(int(p_i.numel()), int(inliers.sum()), T)


def colours_of(view: View) -> np.ndarray:
    """``(H, W, 3)`` uint8: the image :func:`~como3r.prior.base.view_from_colors` turns back
    into ``view.image`` bit for bit (``2 v / 255 - 1`` inverted; every view a robot encodes
    is made from a uint8 image, :func:`~como3r.data.preprocess.make_view`)."""
    pixels = torch.round((view.image.float() * 0.5 + 0.5) * 255.0).clamp(0, 255)
    return pixels.to(torch.uint8).permute(1, 2, 0).contiguous().cpu().numpy()


@dataclass
class Registrar:
    """One robot's encoder and decoder with the caches of F-Sec. III-B.

    Args:
        prior: the prior.
        robot: this robot's id.
        view_of: loads the :class:`View` of one of this robot's keyframes.
        config: registration parameters.
    """

    prior: Prior
    robot: int
    view_of: Callable[[int], View]
    config: RegistrationConfig
    stats: RegistrationStats = field(default_factory=RegistrationStats)
    _own: dict[int, Encoding] = field(default_factory=dict)
    _foreign: dict[tuple[int, int], Encoding] = field(default_factory=dict)
    _consecutive: dict[int, Registration] = field(default_factory=dict)
    _used: set[int] = field(default_factory=set)
    _refused: set[tuple[int, int]] = field(default_factory=set)

    def own_encoding(self, keyframe: int) -> Encoding:
        """The encoding of one of this robot's keyframes, computed once."""
        if keyframe not in self._own:
            view = self.view_of(keyframe)
            start = time.perf_counter()
            self._own[keyframe] = self.prior.encode(view)
            self.stats.encode_seconds += time.perf_counter() - start
            self.stats.encodes += 1
        return self._own[keyframe]

    def scene_depth(self, view: View) -> float:
        """Median depth of the prior's pointmap of ``view``, which must be keyframe 0's (the
        first frame with odometry is always keyframe 0); its encoding is kept as keyframe 0's.

        The robot's length unit (``keyframe_distance_ratio``): the prior's pointmaps are
        metric up to its scale error (MASt3R regresses metric scale), so this is the scene
        depth in odometry units to that error, which only shifts the keyframe spacing.

        Returns:
            The median of the pointmap's positive depths (view decoded with itself), > 0.

        Raises:
            GeometryError: the pointmap has no point in front of the camera.
        """
        start = time.perf_counter()
        encoding = self.prior.encode(view)
        self.stats.encode_seconds += time.perf_counter() - start
        self.stats.encodes += 1
        self._own[0] = encoding
        depth = front_depths(self.prior.decode(encoding, encoding).X_ii.float().cpu())
        if depth.numel() == 0:
            raise GeometryError(
                f"robot {self.robot}: the prior's pointmap of keyframe 0 has no "
                "point in front of the camera"
            )
        return float(depth.median())

    def reply_for_peer(self, keyframe: int) -> dict[str, Any]:
        """What a robot that decodes one of this robot's keyframes receives, as the fields of
        an :class:`~.messages.EncodingReply`: ``colours``, the exact image the prior encoded,
        where the prior encodes images again (:meth:`Prior.can_reencode`); with the
        ``encoding``'s record where the prior makes it again from both
        (:meth:`Encoding.portable`: the simulated prior's ground truth); else ``encoding``.
        """
        self._mark_used(keyframe)
        if self.prior.can_reencode(self.robot):
            return {"colours": colours_of(self.view_of(keyframe))}
        encoding = self.own_encoding(keyframe)
        portable = encoding.portable()
        if isinstance(portable, EncodingRecord):  # the prior makes it from both again
            return {"encoding": portable, "colours": colours_of(self.view_of(keyframe))}
        return {"encoding": encoding.for_decoding()}

    def _mark_used(self, keyframe: int) -> None:
        if keyframe not in self._used:
            self._used.add(keyframe)
            self.stats.registration_encodes += 1

    def has_foreign(self, robot: int, keyframe: int) -> bool:
        """Whether the encoding of ``robot``'s ``keyframe`` has been received."""
        return (robot, keyframe) in self._foreign

    def answered(self, robot: int, keyframe: int) -> bool:
        """Whether the encoding of ``robot``'s ``keyframe`` came (accepted or refused)."""
        return (robot, keyframe) in self._foreign or (robot, keyframe) in self._refused

    def add_foreign(
        self,
        robot: int,
        keyframe: int,
        encoding: Encoding | None = None,
        colours: np.ndarray | None = None,
    ) -> None:
        """Cache an encoding received from another robot, or this robot's encoding of the
        ``(H, W, 3)`` uint8 ``colours`` it sent; refuse (and log) an encoding that this
        robot's prior cannot decode with its own: another encoding type, or a tensor field
        of another dtype or number of dimensions."""
        if colours is not None:
            self._encode_foreign(robot, keyframe, colours, encoding)
            return
        if encoding is None:
            raise ValueError("add_foreign needs an encoding or colours")
        own = self.own_encoding(0)
        why = _mismatch(own, encoding)
        if why is None:
            self._foreign[(robot, keyframe)] = encoding
            return
        logger.warning(
            "robot %d: refused robot %d's encoding of keyframe %d: %s",
            self.robot,
            robot,
            keyframe,
            why,
        )
        self._refused.add((robot, keyframe))

    def _encode_foreign(
        self, robot: int, keyframe: int, colours: np.ndarray, record: Encoding | None
    ) -> None:
        """Encode another robot's keyframe from its colours (and ``record``, an
        :class:`EncodingRecord`, where its prior needs one), or refuse (and log) it."""
        start = time.perf_counter()
        try:
            if record is not None and not isinstance(record, EncodingRecord):
                raise PriorError(f"a {type(record).__name__} came with colours, not a record")
            encoding = self.prior.encode_again(colours, robot, keyframe, record)
        except PriorError as exc:
            logger.warning(
                "robot %d: refused robot %d's keyframe %d: %s", self.robot, robot, keyframe, exc
            )
            self._refused.add((robot, keyframe))
            return
        self.stats.encode_seconds += time.perf_counter() - start
        self.stats.foreign_encodes += 1
        self._foreign[(robot, keyframe)] = encoding

    def register(self, keyframe: int, robot: int, other: int) -> Registration:
        """Register this robot's ``keyframe`` (i) with ``robot``'s keyframe ``other`` (j).

        The encoding of j must have been received (:meth:`add_foreign`).
        """
        self.stats.naive_encodes += 2
        self._mark_used(keyframe)
        enc_i = self.own_encoding(keyframe)
        enc_j = self._foreign[(robot, other)]
        return self._decode(enc_i, enc_j, ("loop", self.robot, keyframe, robot, other))

    def consecutive(self, keyframe: int, count: int) -> tuple[int, Registration]:
        """Registration of ``keyframe`` with its odometry neighbour (F-Eq. 1's denominator),
        cached; ``count`` is the robot's number of keyframes.

        Returns:
            The neighbour (:func:`odometry_neighbour`) and the registration.
        """
        neighbour = odometry_neighbour(keyframe, count)
        if keyframe not in self._consecutive:
            self.stats.naive_encodes += 2
            self._mark_used(keyframe)
            self._mark_used(neighbour)
            enc_i = self.own_encoding(keyframe)
            enc_n = self.own_encoding(neighbour)
            self._consecutive[keyframe] = self._decode(
                enc_i, enc_n, ("odometry", self.robot, keyframe, neighbour)
            )
        return neighbour, self._consecutive[keyframe]

    def register_own(self, keyframe: int, other: int) -> Registration:
        """Registration of two of this robot's keyframes (``T_ij``: ``other`` in
        ``keyframe``), not cached: ``benchmarks/start_scale.py``'s pairs."""
        return self._decode(
            self.own_encoding(keyframe),
            self.own_encoding(other),
            ("own", self.robot, keyframe, other),
        )

    def _decode(self, enc_i: Encoding, enc_j: Encoding, name: tuple) -> Registration:
        start = time.perf_counter()
        pred_ij, pred_ji = self.prior.decode_symmetric([(enc_i, enc_j)])[0]
        pred_ij, pred_ji = pred_ij.to("cpu"), pred_ji.to("cpu")
        self.stats.decode_seconds += time.perf_counter() - start
        self.stats.decodes += 1
        return register_predictions(
            pred_ij, pred_ji, self.config, generator(self.config.seed, *name), self.stats
        )


def _mismatch(own: Encoding, other: Encoding) -> str | None:
    """Why ``other`` cannot be decoded together with ``own`` (None: it can)."""
    if type(other) is not type(own):
        return f"a {type(other).__name__}, where this prior makes {type(own).__name__}"
    for f in fields(own):
        mine, theirs = getattr(own, f.name), getattr(other, f.name)
        if isinstance(mine, Tensor) and (
            not isinstance(theirs, Tensor) or (mine.dtype, mine.ndim) != (theirs.dtype, theirs.ndim)
        ):
            return f"{f.name} is not a {mine.ndim}-d {mine.dtype} tensor"
    return None


def odometry_neighbour(keyframe: int, count: int) -> int:
    """The keyframe paired with ``keyframe`` for F-Eq. 1: its predecessor, or its successor
    for the first keyframe (itself if the robot has a single keyframe)."""
    if keyframe > 0:
        return keyframe - 1
    return 1 if count > 1 else 0

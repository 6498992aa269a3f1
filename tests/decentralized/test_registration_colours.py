"""A robot whose prior encodes images again (MASt3R) sends a registration candidate's
colours, not its encoder tokens; the recipient's encoding of them registers the pair
exactly as the sender's encoding would (issue 39: bytes per registered keyframe)."""

from __future__ import annotations

import numpy as np
import pytest

from como3r.config_decentralized import RegistrationConfig
from como3r.data.preprocess import ImageTransform
from como3r.decentralized.messages import EncodingReply
from como3r.decentralized.registration import Registrar, colours_of
from como3r.errors import MessageError
from como3r.prior.base import View, view_from_colors
from como3r.prior.mast3r.prior import MASt3RPrior
from como3r.prior.mast3r.testing import tiny_network
from como3r.transport import codec


@pytest.fixture(scope="module")
def prior() -> MASt3RPrior:
    return MASt3RPrior(tiny_network(seed=0))


def _views(robot: int, seed: int) -> list[View]:
    rng = np.random.default_rng(seed)
    images = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(3)]
    return [
        View(image=ImageTransform.to_network(image), agent=robot, index=k)
        for k, image in enumerate(images)
    ]


def test_every_uint8_image_comes_back_bit_for_bit() -> None:
    values = np.arange(256, dtype=np.uint8).reshape(16, 16, 1).repeat(3, axis=2)
    view = View(image=ImageTransform.to_network(values))
    assert np.array_equal(colours_of(view), values)
    assert bool((view_from_colors(colours_of(view), 0, 0).image == view.image).all())


def test_the_recipient_encodes_the_colours_and_registers_as_with_the_encoding(prior) -> None:
    theirs, mine = _views(1, seed=1), _views(0, seed=2)
    sender = Registrar(prior, 1, theirs.__getitem__, RegistrationConfig())
    payload = sender.reply_for_peer(2)
    assert set(payload) == {"colours"} and payload["colours"].dtype == np.uint8
    reply = EncodingReply(sender=1, recipient=0, round=0, time_s=0.5, keyframe=2, **payload)
    received = codec.decode(codec.encode(reply, lossy=True))  # lossless WebP on the wire
    assert received.encoding is None and np.array_equal(received.colours, payload["colours"])

    by_colours = Registrar(prior, 0, mine.__getitem__, RegistrationConfig())
    by_colours.add_foreign(1, 2, received.encoding, received.colours)
    by_encoding = Registrar(prior, 0, mine.__getitem__, RegistrationConfig())
    by_encoding.add_foreign(1, 2, encoding=sender.own_encoding(2))
    assert by_colours.stats.foreign_encodes == 1 and by_encoding.stats.foreign_encodes == 0
    one, other = by_colours.register(0, 1, 2), by_encoding.register(0, 1, 2)
    assert one.correspondences == other.correspondences and one.inliers == other.inliers
    if one.T_ij is None:
        assert other.T_ij is None
    else:
        assert bool((one.T_ij == other.T_ij).all())


def test_a_reply_with_neither_or_colours_beside_an_encoding_is_refused(prior) -> None:
    view = _views(1, seed=3)[0]
    encoding = prior.encode(view)
    for fields, message in (
        ({}, "an encoding or colours"),
        ({"encoding": encoding, "colours": colours_of(view)}, "never with an encoding"),
    ):
        reply = EncodingReply(sender=1, recipient=0, round=0, time_s=0.5, keyframe=0, **fields)
        with pytest.raises(MessageError, match=message):
            codec.decode(codec.encode(reply))

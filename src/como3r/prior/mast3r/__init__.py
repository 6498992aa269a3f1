"""Our own implementation of the MASt3R network (MAST3R_SPEC.md), loading the official weights.

Public API::

    prior = load_mast3r(checkpoint_path, device="cpu", dtype=torch.float32)
    enc = prior.encode(view_or_image)          # MASt3REncoding (tokens after enc_norm)
    pred = prior.decode(enc_i, enc_j)          # PairPrediction in camera i
    preds = prior.decode_symmetric([(enc_i, enc_j), ...])
"""

from como3r.prior.mast3r.config import RELEASED_MODEL_STRING, MASt3RConfig, parse_model_string
from como3r.prior.mast3r.loader import KNOWN_UNUSED, is_known_unused, load_network, read_checkpoint
from como3r.prior.mast3r.model import MASt3RNetwork
from como3r.prior.mast3r.prior import (
    MASt3REncoding,
    MASt3RPrior,
    SupportsRetrievalFeatures,
    load_mast3r,
)

__all__ = [
    "KNOWN_UNUSED",
    "MASt3RConfig",
    "MASt3REncoding",
    "MASt3RNetwork",
    "MASt3RPrior",
    "RELEASED_MODEL_STRING",
    "SupportsRetrievalFeatures",
    "is_known_unused",
    "load_mast3r",
    "load_network",
    "parse_model_string",
    "read_checkpoint",
]

"""One interface test suite for every prior (DESIGN.md, "The prior interface").

Everything above ``prior/`` relies on these properties alone, so both the simulated
sensor and the MASt3R network (a tiny random configuration here) must satisfy them.
"""

from __future__ import annotations

import pytest
import torch
from scipy.spatial.transform import Rotation

from como3r.data.preprocess import ImageTransform
from como3r.data.synth import Intrinsics, Renderer, build_preset
from como3r.prior.base import Encoding, PairPrediction, Prior, View
from como3r.prior.ground_truth import GroundTruth, InMemoryTruth
from como3r.prior.mast3r.prior import MASt3RPrior
from como3r.prior.mast3r.retrieval import RetrievalHead
from como3r.prior.mast3r.testing import tiny_network
from como3r.prior.simulated import SimulatedPrior

W, H = 64, 48


def _tiny_mast3r() -> Prior:
    prior = MASt3RPrior(tiny_network(seed=0))
    prior.retrieval = RetrievalHead(in_dim=32, hdims=(16,)).eval()
    return prior


#: ground truth of the rendered views, the simulated prior's source
TRUTH = InMemoryTruth()
PRIORS = {"simulated": lambda: SimulatedPrior(truth=TRUTH), "mast3r-tiny": _tiny_mast3r}


@pytest.fixture(scope="module")
def views() -> list[View]:
    spec = build_preset("default", 1, 30, 0.2, seed=2)
    intrinsics = Intrinsics.from_hfov(W, H, 75.0)
    renderer = Renderer(spec.scene, intrinsics)
    out = []
    for index in (5, 7):
        R_WC, t_WC = spec.paths[0].rotations[index], spec.paths[0].positions[index]
        frame = renderer.render(R_WC, t_WC)
        quat = Rotation.from_matrix(R_WC).as_quat()
        out.append(View(ImageTransform.to_network(frame.rgb), agent=1, index=index))
        TRUTH.add(
            1,
            index,
            GroundTruth(
                depth=torch.from_numpy(frame.depth),
                K=torch.from_numpy(intrinsics.matrix()).float(),
                surface=torch.from_numpy(frame.surface),
                T_WC=torch.tensor([*t_WC, *quat, 1.0], dtype=torch.float64),
            ),
        )
    return out


@pytest.fixture(scope="module", params=sorted(PRIORS))
def prior(request) -> Prior:
    return PRIORS[request.param]()


def _check_prediction(pred: PairPrediction, d: int) -> None:
    for name in ("X_ii", "X_ji"):
        assert getattr(pred, name).shape == (H, W, 3)
    for name in ("C_ii", "C_ji", "Q_ii", "Q_ji"):
        assert getattr(pred, name).shape == (H, W)
    for name in ("D_ii", "D_ji"):
        assert getattr(pred, name).shape == (H, W, d)
        norms = getattr(pred, name).norm(dim=-1)
        assert torch.allclose(norms, torch.ones_like(norms), atol=1e-4)
    for value in (pred.X_ii, pred.X_ji, pred.C_ii, pred.C_ji, pred.Q_ii, pred.Q_ji):
        assert value.dtype == torch.float32
        assert bool(torch.isfinite(value).all())
    assert bool((pred.C_ii >= 1).all()) and bool((pred.C_ji >= 1).all())
    assert bool((pred.Q_ii > 0).all()) and bool((pred.Q_ji > 0).all())


def test_encode_keeps_identity(prior: Prior, views: list[View]) -> None:
    enc = prior.encode(views[0])
    assert isinstance(enc, Encoding)
    assert (enc.agent, enc.index, tuple(enc.shape)) == (1, 5, (H, W))


def test_decode_outputs_have_the_documented_types_shapes_and_ranges(prior, views) -> None:
    enc_i, enc_j = prior.encode(views[0]), prior.encode(views[1])
    _check_prediction(prior.decode(enc_i, enc_j), prior.descriptor_dim)
    _check_prediction(prior.decode(enc_i, enc_i), prior.descriptor_dim)
    assert prior.descriptor_dim == 24


def test_decode_is_deterministic(prior, views) -> None:
    enc_i, enc_j = prior.encode(views[0]), prior.encode(views[1])
    a, b = prior.decode(enc_i, enc_j), prior.decode(enc_i, enc_j)
    assert torch.equal(a.X_ji, b.X_ji) and torch.equal(a.D_ii, b.D_ii)


def test_symmetric_decode_matches_single_decodes(prior, views) -> None:
    enc_i, enc_j = prior.encode(views[0]), prior.encode(views[1])
    ((ij, ji),) = prior.decode_symmetric([(enc_i, enc_j)])
    for batched, single in ((ij, prior.decode(enc_i, enc_j)), (ji, prior.decode(enc_j, enc_i))):
        assert torch.allclose(batched.X_ji, single.X_ji, atol=1e-4, rtol=1e-4)
        assert torch.allclose(batched.C_ii, single.C_ii, atol=1e-4, rtol=1e-4)


def test_retrieval_features_are_finite_local_descriptors(prior, views) -> None:
    desc, attention = prior.retrieval_features(prior.encode(views[0]))
    assert desc.ndim == 2 and attention.shape == (desc.shape[0],)
    assert desc.shape[0] > 0
    assert bool(torch.isfinite(desc).all()) and bool(torch.isfinite(attention).all())


def test_describe_names_the_prior(prior) -> None:
    info = prior.describe()
    assert isinstance(info, dict) and info

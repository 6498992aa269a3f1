"""A small ring scene's keyframes as an agent would send them, for coordinator tests that feed
packets straight to a :class:`~como3r.coordination.coordinator.Coordinator`."""

from __future__ import annotations

from pathlib import Path

from torch import Tensor

from como3r.config import Config
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.preprocess import make_view
from como3r.data.synth import synthesize
from como3r.frontend.packets import KeyframePacket
from como3r.frontend.pairs import link_pairs
from como3r.prior.base import Encoding, EncodingRecord, PairPrediction, Prior, View
from como3r.prior.simulated import SimulatedPrior
from como3r.runtime.pipeline import _colors

WIDTH, HEIGHT = 64, 48
AGENTS = 3
#: a short run: few BA iterations, one cleanup pass, no depth alternation
SHORT_RUN = [
    f"input.long_side={WIDTH}",
    "global_ba.max_iters_stream=5",
    "global_ba.max_iters_cleanup=5",
    "global_ba.cleanup_passes=1",
    "depth.alternation_rounds=0",
]


def ring_keyframes(
    root: Path, config: Config, agents: int, width: int, height: int, portable_from: int | None
) -> tuple[SimulatedPrior, list[KeyframePacket]]:
    """``agents`` agents on a ring (overlap 0.5, 8 frames each, seed 0), every second frame a
    keyframe, interleaved in time; agents from ``portable_from`` on send encoding records (as
    a multi-process run does: the coordinator encodes their keyframes again), the others
    their encodings (None: every agent its encoding)."""
    synthesize(
        root,
        agents=agents,
        seed=0,
        overlap=0.5,
        frames=8,
        preset="default",
        width=width,
        height=height,
    )
    opened = {a: open_agent(root / f"agent_{a}") for a in range(agents)}
    prior = SimulatedPrior(config.simulated_prior, AgentFolderTruth(opened, width))
    packets: dict[int, list[KeyframePacket]] = {}
    for a, agent in opened.items():
        packets[a], previous = [], None
        portable = portable_from is not None and a >= portable_from
        for kf_id, index in enumerate(range(0, agent.num_frames, 2)):
            frame = agent.load_frame(index)
            view = make_view(frame, a, width)
            enc = prior.encode(view)
            packets[a].append(
                keyframe_packet(
                    prior,
                    config,
                    view,
                    enc,
                    prior.decode(enc, enc),
                    previous,
                    kf_id=kf_id,
                    frame_index=index,
                    timestamp=frame.timestamp,
                    T_WC=agent.groundtruth.T_WC[index].clone(),
                    encoding=enc.portable() if portable else enc,
                )
            )
            previous = enc
    order = [
        p for k in range(len(packets[0])) for a in range(agents) for p in packets[a][k : k + 1]
    ]
    return prior, order


def keyframe_packet(
    prior: Prior,
    config: Config,
    view: View,
    enc: Encoding,
    pred: PairPrediction,
    previous: Encoding | None,
    *,
    kf_id: int,
    frame_index: int,
    timestamp: float,
    T_WC: Tensor,
    encoding: Encoding | EncodingRecord,
) -> KeyframePacket:
    """A keyframe of agent ``view.agent`` as its front-end sends it: its canonical pointmap
    (``pred``, the prior's self-decode of ``enc``) and its sequential edge to the agent's
    previous keyframe (``previous``'s encoding; None for its first), decoded and matched
    here."""
    link = (
        None
        if previous is None
        else link_pairs(prior, [(previous, enc)], config.matching, config.tracking.q_min)[0]
    )
    return KeyframePacket(
        agent=view.agent,
        kf_id=kf_id,
        frame_index=frame_index,
        timestamp=timestamp,
        T_WC=T_WC,
        X_hat=pred.X_ii,
        C_hat=pred.C_ii,
        colors=_colors(view),
        encoding=encoding,
        retrieval=prior.retrieval_features(enc),
        sequential_ij=None if link is None else link.ij,
        sequential_ji=None if link is None else link.ji,
        previous=None,
    )

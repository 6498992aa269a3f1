"""Retrieval hits from the features as the lossy wire delivers them against float32 ones (a
script, not a test).

Keyframe retrieval features travel in 8 bits with a scale per descriptor across machines
(``transport/codec_compact.py``; float16 before). This
runs the simulated front-end over every frame of both agents of a folder, then feeds the
keyframes in time order to two coordinator retrieval databases (binary ASMK,
``coordination.association.CrossAgentRetrieval``), one with the features as made, one with
them as the wire delivers them, and compares every query's hits and similarities; once with the
agents' visual words (the coordinator's codebook is theirs), once with the coordinator
quantising the descriptors itself.

Measured (``como3r synth --agents 2 --frames 16 --width 640 --height 480``, 17 keyframes,
300 x 128 descriptors): with float16 features, identical hit lists for 17 of 17 queries (15
hits), similarities identical to the last bit, both ways; with the 8-bit coding, identical
hit lists for 17 of 17 queries (15 hits) both ways, similarities within 4.4e-4.

    como3r synth --out /tmp/s2 --agents 2 --frames 16 --width 640 --height 480
    python benchmarks/retrieval_precision.py /tmp/s2
"""

import argparse
from pathlib import Path

import torch

from como3r.config import Config
from como3r.coordination.association import CrossAgentRetrieval
from como3r.data.agent import open_agent
from como3r.data.preprocess import upsampling
from como3r.frontend.agent import AgentFrontend
from como3r.prior.retrieval import Quantized
from como3r.runtime.pipeline import PriorSpec, build_prior, load_frame
from como3r.transport.codec_arrays import Budget
from como3r.transport.codec_compact import coded_from_wire, coded_to_wire


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=Path, help="a folder with agent_0 and agent_1")
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = Config()
    agents = {k: open_agent(args.scene / f"agent_{k}") for k in (0, 1)}
    prior, codebook = build_prior(PriorSpec("simulated"), config, agents)
    packets = []
    for k, agent in agents.items():
        frontend = AgentFrontend(
            prior, config, k, codebook, upsampling(agent.image_size, config.input.long_side)
        )
        for i in range(agent.num_frames):
            frontend.process(*load_frame(agent, k, i, config.input.long_side, False))
            packets.extend(frontend.drain_new_keyframes())
    packets.sort(key=lambda p: p.timestamp)
    print(f"{len(packets)} keyframes, descriptors {tuple(packets[0].retrieval[0].shape)}")
    for words in (True, False):
        runs = {}
        for half in (False, True):
            database = CrossAgentRetrieval(codebook, config.retrieval)
            hits = []
            for p in packets:
                descriptors, attention = p.retrieval
                if half:  # as the lossy wire delivers them (8 bits, codec_compact)
                    received = coded_from_wire(
                        coded_to_wire("retrieval", p.retrieval), "retrieval", Budget(2**40)
                    )
                    descriptors, attention = received
                if words and p.retrieval_words is not None:
                    descriptors = Quantized(descriptors, p.retrieval_words)
                hits.append(database.query_and_add(p.agent, p.kf_id, (descriptors, attention)))
            runs[half] = hits
        same = sum([h[:2] for h in a] == [h[:2] for h in b] for a, b in zip(*runs.values()))
        diffs = [
            abs(x.similarity - y.similarity) for a, b in zip(*runs.values()) for x, y in zip(a, b)
        ]
        print(
            f"{'agents words' if words else 'coordinator quantises'}: identical hit lists "
            f"{same}/{len(packets)}, hits {sum(map(len, runs[False]))} vs "
            f"{sum(map(len, runs[True]))}, largest similarity difference "
            f"{max(diffs, default=0.0):.2e}"
        )


if __name__ == "__main__":
    main()

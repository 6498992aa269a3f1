"""Frame sources: agent inputs (image folders, videos), MASt3R pre-processing, stream
splitting, and the synthetic scene generator (``como3r.data.synth``)."""

from como3r.data.agent import open_agent
from como3r.data.agent_input import AgentInput, Frame
from como3r.data.preprocess import ImageTransform, compute_transform, make_view, resize_crop
from como3r.data.split import chunk_ranges, split_sequence

__all__ = [
    "AgentInput",
    "Frame",
    "ImageTransform",
    "chunk_ranges",
    "compute_transform",
    "make_view",
    "open_agent",
    "resize_crop",
    "split_sequence",
]

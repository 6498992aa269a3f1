"""Synthetic multi-agent outdoor scenes with exact ground truth (``como3r synth``).

:func:`synthesize` writes one agent input folder per agent (manual: docs/inputs.md, "Agent
input") plus ``scene.json``; the presets are described in :mod:`.presets` and
:mod:`.families`, the rendering in :mod:`.render` and the appearance keys in
:mod:`.textures`.
"""

from como3r.data.synth.families import PRESETS, build_preset
from como3r.data.synth.presets import SceneSpec
from como3r.data.synth.render import Frame, Intrinsics, Renderer, Scene
from como3r.data.synth.writer import FRAME_RATE, HFOV_DEG, synthesize

__all__ = [
    "FRAME_RATE",
    "HFOV_DEG",
    "PRESETS",
    "Frame",
    "Intrinsics",
    "Renderer",
    "Scene",
    "SceneSpec",
    "build_preset",
    "synthesize",
]

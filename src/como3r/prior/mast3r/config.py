"""Typed configuration of the MASt3R network and the parser of its constructor string.

The official checkpoint stores the network as a Python expression in ``ckpt['args'].model``
(MAST3R_SPEC.md §1.3), e.g. ``AsymmetricMASt3R(pos_embed='RoPE100', enc_embed_dim=1024, ...)``.
The official loader runs it with ``eval``; we never do. :func:`parse_model_string` walks the
expression with :mod:`ast`, accepts keyword arguments whose values are literals (numbers,
strings, booleans, tuples, ``inf``) and turns them into a frozen :class:`MASt3RConfig`.

The loader's rewrite rules (spec §1.4 step 2) are applied on the parsed values rather than on
the text: ``patch_embed_cls='ManyAR_PatchEmbed'`` becomes ``'PatchEmbedDust3R'`` (same
weights, no transposition of portrait images) and ``landscape_only`` is forced to ``False``.
"""

from __future__ import annotations

import ast
import math
import re
from dataclasses import dataclass
from typing import Any

from como3r.errors import CheckpointError, ConfigError

#: the constructor string the released checkpoint was trained with (spec §1.3)
RELEASED_MODEL_STRING = (
    "AsymmetricMASt3R(pos_embed='RoPE100', patch_embed_cls='ManyAR_PatchEmbed', "
    "img_size=(512, 512), head_type='catmlp+dpt', output_mode='pts3d+desc24', "
    "depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), enc_embed_dim=1024, "
    "enc_depth=24, enc_num_heads=16, dec_embed_dim=768, dec_depth=12, dec_num_heads=12, "
    "two_confs=True, desc_conf_mode=('exp', 0, inf))"
)

_MODEL_CLASS = "AsymmetricMASt3R"
_PATCH_EMBED_CLASSES = ("PatchEmbedDust3R", "ManyAR_PatchEmbed")

#: arguments the string must name: they fix the tensor shapes
_REQUIRED = (
    "enc_embed_dim",
    "enc_depth",
    "enc_num_heads",
    "dec_embed_dim",
    "dec_depth",
    "dec_num_heads",
    "pos_embed",
    "head_type",
    "output_mode",
)

#: defaults of the official constructors for the optional arguments (spec §1.3, §5.4)
_OPTIONAL_DEFAULTS: dict[str, Any] = {
    "img_size": 224,
    "patch_size": 16,
    "mlp_ratio": 4.0,
    "norm_im2_in_dec": True,
    "depth_mode": ("exp", -math.inf, math.inf),
    "conf_mode": ("exp", 1, math.inf),
    "desc_mode": "norm",
    "two_confs": False,
    "desc_conf_mode": None,  # None: same as conf_mode
    "patch_embed_cls": "PatchEmbedDust3R",
    "landscape_only": False,
    "freeze": "none",
    "mask_ratio": 0.9,
}

_ROPE_PATTERN = re.compile(r"^RoPE(\d+(?:\.\d*)?)$")
_DESC_PATTERN = re.compile(r"^pts3d\+desc(\d+)$")


@dataclass(frozen=True)
class MASt3RConfig:
    """Hyper-parameters of the network (spec §1.3). Defaults are the released checkpoint's.

    Attributes:
        enc_embed_dim, enc_depth, enc_num_heads: ViT encoder width, blocks, heads.
        dec_embed_dim, dec_depth, dec_num_heads: width, blocks and heads of each decoder.
        patch_size: patch side in pixels; the DPT head's up-sampling factors fix it to 16.
        mlp_ratio: MLP hidden width over token width, in encoder and decoder blocks.
        norm_im2_in_dec: decoder blocks layer-normalise the other view's tokens (``norm_y``).
        rope_base: base frequency of the 2-D RoPE (``'RoPE100'`` -> 100.0).
        desc_dim: local descriptor dimension (``output_mode='pts3d+desc24'`` -> 24).
        two_confs: descriptors get their own confidence channel.
        conf_min, conf_max: ``conf = conf_min + min(exp(x), conf_max - conf_min)``.
        desc_conf_min, desc_conf_max: the same for the descriptor confidence.
    """

    enc_embed_dim: int = 1024
    enc_depth: int = 24
    enc_num_heads: int = 16
    dec_embed_dim: int = 768
    dec_depth: int = 12
    dec_num_heads: int = 12
    patch_size: int = 16
    mlp_ratio: float = 4.0
    norm_im2_in_dec: bool = True
    rope_base: float = 100.0
    desc_dim: int = 24
    two_confs: bool = True
    conf_min: float = 1.0
    conf_max: float = math.inf
    desc_conf_min: float = 0.0
    desc_conf_max: float = math.inf

    def __post_init__(self) -> None:
        for name in (
            "enc_embed_dim",
            "enc_depth",
            "enc_num_heads",
            "dec_embed_dim",
            "dec_depth",
            "dec_num_heads",
            "desc_dim",
        ):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"MASt3R {name} must be a positive integer, got {value!r}")
        for prefix in ("enc", "dec"):
            dim = getattr(self, f"{prefix}_embed_dim")
            heads = getattr(self, f"{prefix}_num_heads")
            # RoPE splits each head into a row half and a column half, each rotated in pairs
            if dim % heads or (dim // heads) % 4:
                raise ConfigError(
                    f"MASt3R {prefix}_embed_dim={dim} must split into {prefix}_num_heads={heads}"
                    " heads whose dimension is a multiple of 4 (2-D RoPE)"
                )
        if self.patch_size != 16:
            raise ConfigError(
                f"MASt3R patch_size={self.patch_size} is not supported: the DPT head up-samples"
                " the token grid by exactly 16"
            )
        if not self.mlp_ratio > 0:
            raise ConfigError(f"MASt3R mlp_ratio must be positive, got {self.mlp_ratio!r}")
        if not (self.rope_base > 0 and math.isfinite(self.rope_base)):
            raise ConfigError(f"MASt3R RoPE base must be positive, got {self.rope_base!r}")
        if not self.conf_max > self.conf_min or not self.desc_conf_max > self.desc_conf_min:
            raise ConfigError("MASt3R confidence modes need vmax > vmin")

    @property
    def enc_head_dim(self) -> int:
        """Per-head dimension of the encoder attention."""
        return self.enc_embed_dim // self.enc_num_heads

    @property
    def dec_head_dim(self) -> int:
        """Per-head dimension of the decoder attention."""
        return self.dec_embed_dim // self.dec_num_heads

    @property
    def dpt_hooks(self) -> tuple[int, int, int, int]:
        """Indices into the decoder's layer list (0 = encoder output) read by the DPT (§5.1)."""
        depth = self.dec_depth
        return (0, depth * 2 // 4, depth * 3 // 4, depth)

    @property
    def local_channels(self) -> int:
        """Channels per pixel of the local-feature MLP: descriptor (+ its confidence)."""
        return self.desc_dim + int(self.two_confs)


def _literal(node: ast.expr, name: str) -> Any:
    """Value of a literal expression node; ``inf`` and ``float('inf')`` are allowed."""
    if isinstance(node, ast.Constant) and isinstance(
        node.value, (int, float, str, bool, type(None))
    ):
        return node.value
    if isinstance(node, (ast.Tuple, ast.List)):
        return tuple(_literal(element, name) for element in node.elts)
    if isinstance(node, ast.Name) and node.id == "inf":
        return math.inf
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        operand = _literal(node.operand, name)
        if isinstance(operand, (int, float)) and not isinstance(operand, bool):
            return -operand if isinstance(node.op, ast.USub) else operand
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id == "float"
        and len(node.args) == 1
        and not node.keywords
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    ):
        text = node.args[0].value.strip().lower()
        if text in ("inf", "+inf", "-inf", "infinity", "-infinity"):
            return float(text)
    raise CheckpointError(
        f"MASt3R constructor argument {name!r} is not a literal value: {ast.unparse(node)!r}"
    )


def _exp_mode(value: Any, name: str) -> tuple[float, float]:
    """Bounds ``(vmin, vmax)`` of an ``('exp', vmin, vmax)`` post-processing mode."""
    if (
        isinstance(value, tuple)
        and len(value) == 3
        and value[0] == "exp"
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value[1:])
    ):
        return float(value[1]), float(value[2])
    raise CheckpointError(
        f"MASt3R {name}={value!r} is not supported (expected ('exp', vmin, vmax))"
    )


def _integer(value: Any, name: str) -> int:
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    raise CheckpointError(f"MASt3R constructor argument {name!r} must be an integer, got {value!r}")


def _parse_call(text: str) -> dict[str, Any]:
    """Keyword arguments of the ``AsymmetricMASt3R(...)`` call in ``text``."""
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as error:
        raise CheckpointError(f"MASt3R constructor string is not valid syntax: {text!r}") from error
    call = tree.body
    if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Name)):
        raise CheckpointError(f"MASt3R constructor string is not a class call: {text!r}")
    if call.func.id != _MODEL_CLASS:
        raise CheckpointError(
            f"unsupported model class {call.func.id!r} in constructor string "
            f"(expected {_MODEL_CLASS})"
        )
    if call.args or any(keyword.arg is None for keyword in call.keywords):
        raise CheckpointError("MASt3R constructor string must use keyword arguments only")
    values: dict[str, Any] = {}
    for keyword in call.keywords:
        values[keyword.arg] = _literal(keyword.value, keyword.arg)
    return values


def parse_model_string(text: str) -> MASt3RConfig:
    """Parse the checkpoint's constructor string into a :class:`MASt3RConfig` without eval.

    Args:
        text: e.g. :data:`RELEASED_MODEL_STRING`.

    Raises:
        CheckpointError: the string is not an ``AsymmetricMASt3R(...)`` call with literal
            keyword arguments, names an unknown argument, lacks a required one, or sets a
            value this implementation does not support. The message names the argument.
    """
    values = _parse_call(text)
    unknown = sorted(set(values) - set(_REQUIRED) - set(_OPTIONAL_DEFAULTS))
    if unknown:
        raise CheckpointError(f"unknown MASt3R constructor argument(s): {', '.join(unknown)}")
    missing = [name for name in _REQUIRED if name not in values]
    if missing:
        raise CheckpointError(f"MASt3R constructor string lacks argument(s): {', '.join(missing)}")
    args = {**_OPTIONAL_DEFAULTS, **values}

    rope = _ROPE_PATTERN.match(str(args["pos_embed"]))
    if rope is None:
        raise CheckpointError(
            f"MASt3R pos_embed={args['pos_embed']!r} is not supported (expected 'RoPE<base>')"
        )
    if args["head_type"] != "catmlp+dpt":
        raise CheckpointError(
            f"MASt3R head_type={args['head_type']!r} is not supported (expected 'catmlp+dpt')"
        )
    desc = _DESC_PATTERN.match(str(args["output_mode"]))
    if desc is None:
        raise CheckpointError(
            f"MASt3R output_mode={args['output_mode']!r} is not supported "
            "(expected 'pts3d+desc<d>')"
        )
    if args["desc_mode"] != "norm":
        raise CheckpointError(
            f"MASt3R desc_mode={args['desc_mode']!r} is not supported (expected 'norm')"
        )
    depth_min, depth_max = _exp_mode(args["depth_mode"], "depth_mode")
    if math.isfinite(depth_min) or math.isfinite(depth_max):
        raise CheckpointError(
            f"MASt3R depth_mode={args['depth_mode']!r} is not supported "
            "(the 'exp' depth mode has no bounds)"
        )
    if args["conf_mode"] is None:
        raise CheckpointError("MASt3R conf_mode=None is not supported: confidences are required")
    conf_min, conf_max = _exp_mode(args["conf_mode"], "conf_mode")
    desc_conf_mode = (
        args["desc_conf_mode"] if args["desc_conf_mode"] is not None else args["conf_mode"]
    )
    desc_conf_min, desc_conf_max = _exp_mode(desc_conf_mode, "desc_conf_mode")
    if args["patch_embed_cls"] not in _PATCH_EMBED_CLASSES:
        raise CheckpointError(
            f"MASt3R patch_embed_cls={args['patch_embed_cls']!r} is not "
            f"supported (expected one of {_PATCH_EMBED_CLASSES})"
        )
    for name in ("two_confs", "norm_im2_in_dec", "landscape_only"):
        if not isinstance(args[name], bool):
            raise CheckpointError(f"MASt3R {name} must be True or False, got {args[name]!r}")
    patch_size = _integer(args["patch_size"], "patch_size")
    img_size = args["img_size"]
    sizes = img_size if isinstance(img_size, tuple) else (img_size, img_size)
    if len(sizes) != 2 or any(_integer(s, "img_size") % patch_size for s in sizes):
        raise CheckpointError(f"MASt3R img_size={img_size!r} must be multiples of the patch size")
    if not isinstance(args["mlp_ratio"], (int, float)) or isinstance(args["mlp_ratio"], bool):
        raise CheckpointError(f"MASt3R mlp_ratio must be a number, got {args['mlp_ratio']!r}")
    try:
        return MASt3RConfig(
            enc_embed_dim=_integer(args["enc_embed_dim"], "enc_embed_dim"),
            enc_depth=_integer(args["enc_depth"], "enc_depth"),
            enc_num_heads=_integer(args["enc_num_heads"], "enc_num_heads"),
            dec_embed_dim=_integer(args["dec_embed_dim"], "dec_embed_dim"),
            dec_depth=_integer(args["dec_depth"], "dec_depth"),
            dec_num_heads=_integer(args["dec_num_heads"], "dec_num_heads"),
            patch_size=patch_size,
            mlp_ratio=float(args["mlp_ratio"]),
            norm_im2_in_dec=args["norm_im2_in_dec"],
            rope_base=float(rope.group(1)),
            desc_dim=int(desc.group(1)),
            two_confs=args["two_confs"],
            conf_min=conf_min,
            conf_max=conf_max,
            desc_conf_min=desc_conf_min,
            desc_conf_max=desc_conf_max,
        )
    except ConfigError as error:
        raise CheckpointError(str(error)) from error

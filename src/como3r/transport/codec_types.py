"""The checks of decoded messages (:mod:`como3r.transport.codec`): a field's value against its
dataclass annotation, and the helpers of the per-type checks
(:func:`~como3r.transport.codec_registry.add_check`) that messages register.
"""

from __future__ import annotations

import types
import typing
from typing import Any, Union

import numpy as np
from torch import Tensor

from como3r.errors import MessageError


def conforms(value: Any, hint: Any) -> bool:
    """Whether a decoded value matches a (resolved) type annotation."""
    if hint is Any:
        return True
    if hint is None or hint is type(None):
        return value is None
    origin = typing.get_origin(hint)
    if origin is Union or origin is types.UnionType:
        return any(conforms(value, h) for h in typing.get_args(hint))
    if origin is typing.Literal:
        return value in typing.get_args(hint)
    if origin is tuple:
        return _conforms_tuple(value, typing.get_args(hint))
    if origin is list:
        (item,) = typing.get_args(hint) or (Any,)
        return isinstance(value, list) and all(conforms(v, item) for v in value)
    if origin is dict:
        key, item = typing.get_args(hint) or (Any, Any)
        return isinstance(value, dict) and all(
            conforms(k, key) and conforms(v, item) for k, v in value.items()
        )
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if isinstance(hint, type):
        return isinstance(value, hint)
    raise TypeError(f"unsupported annotation {hint!r} on a registered message type")


def _conforms_tuple(value: Any, args: tuple) -> bool:
    if not isinstance(value, tuple):
        return False
    if not args:
        return True
    if len(args) == 2 and args[1] is Ellipsis:
        return all(conforms(v, args[0]) for v in value)
    return len(value) == len(args) and all(conforms(v, a) for v, a in zip(value, args))


def hint_name(hint: Any) -> str:
    return getattr(hint, "__name__", None) or repr(hint).replace("typing.", "")


def require(ok: bool, what: str) -> None:
    """For the per-type checks of :func:`add_check`: raise :class:`MessageError` ``what``
    unless ``ok``."""
    if not ok:
        raise MessageError(what)


def require_shape(x: Tensor | np.ndarray, shape: tuple[int | None, ...], name: str) -> None:
    """For the per-type checks: ``x.shape`` matches ``shape`` (None matches any size)."""
    matches = len(x.shape) == len(shape) and all(
        s is None or s == n for s, n in zip(shape, x.shape)
    )
    require(
        matches,
        f"{name} has shape {tuple(x.shape)}, expected "
        f"({', '.join('*' if s is None else str(s) for s in shape)})",
    )

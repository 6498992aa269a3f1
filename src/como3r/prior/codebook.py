"""ASMK codebooks of the place retrieval (:mod:`como3r.prior.retrieval`): the official
release's codebook is a pickle, which :func:`load_codebook` reads with a restricted
unpickler that admits only the numpy objects an array needs; :func:`train_codebook` trains
one by k-means (the simulated prior's).
"""

from __future__ import annotations

import importlib
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import torch

from como3r.errors import CheckpointError, InputError


def _numpy_core(submodule: str) -> Any:
    """``numpy._core.<submodule>`` (numpy >= 2) or ``numpy.core.<submodule>`` (numpy 1)."""
    try:
        return importlib.import_module(f"numpy._core.{submodule}")
    except ImportError:
        return importlib.import_module(f"numpy.core.{submodule}")


def _latin1_encode(text: str, encoding: str) -> bytes:
    """The only use of ``_codecs.encode`` in a protocol-2 numpy pickle: raw array bytes."""
    if encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError(f"refused _codecs.encode with encoding {encoding!r}")
    return text.encode("latin1")


def _allowed_globals() -> dict[tuple[str, str], Any]:
    """Every global a pickled dict of numpy arrays can reference, by (module, name).

    Pickles written under numpy 1 name ``numpy.core``, under numpy 2 ``numpy._core``; both
    spellings resolve to the installed numpy's functions.
    """
    multiarray, numeric = _numpy_core("multiarray"), _numpy_core("numeric")
    allowed: dict[tuple[str, str], Any] = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("_codecs", "encode"): _latin1_encode,
    }
    for package in ("numpy.core", "numpy._core"):
        allowed[(f"{package}.multiarray", "_reconstruct")] = multiarray._reconstruct
        allowed[(f"{package}.multiarray", "scalar")] = multiarray.scalar
        allowed[(f"{package}.numeric", "_frombuffer")] = numeric._frombuffer
    return allowed


class _RefusedGlobal(pickle.UnpicklingError):
    """A pickle referenced a global outside the allow-list."""

    def __init__(self, qualified_name: str) -> None:
        super().__init__(qualified_name)
        self.qualified_name = qualified_name


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that resolves only numpy array / dtype / scalar reconstruction globals.

    Anything else (``os.system``, ``builtins.eval``, ``subprocess.Popen``...) is refused
    before it is looked up, so a malicious file cannot run code.
    """

    _allowed = _allowed_globals()

    def find_class(self, module: str, name: str) -> Any:
        try:
            return self._allowed[(module, name)]
        except KeyError:
            raise _RefusedGlobal(f"{module}.{name}") from None


def _codebook_size(size: Any, path: Path) -> int:
    """Number of centroids of asmk's ``params['size']``: an int or a string like ``'64k'``."""
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        return int(size)
    if isinstance(size, str) and size[:-1].isdigit() and size[-1:] in ("k", "M"):
        return int(size[:-1]) * {"k": 1024, "M": 1024**2}[size[-1]]
    raise CheckpointError(f"{path}: codebook params.size {size!r} is not a codebook size")


def load_codebook(path: str | Path) -> np.ndarray:
    """Read an asmk codebook pickle (MAST3R_SPEC.md §8.1) without executing code.

    The file holds ``{'type': 'Codebook', 'params': {'size': K or '64k'},
    'state': {'centroids': ndarray (K, d)}}`` as written by ``asmk.codebook.Codebook``.

    Returns:
        ``(K, d)`` float32 C-contiguous centroids.

    Raises:
        CheckpointError: unreadable, truncated or malformed file, or a pickle that imports
            anything but numpy array reconstruction (the refused global is named).
    """
    path = Path(path)
    try:
        with path.open("rb") as handle:
            state = _NumpyOnlyUnpickler(handle).load()
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read codebook ({exc.strerror})") from None
    except _RefusedGlobal as exc:
        raise CheckpointError(
            f"{path}: refused to load codebook: the pickle imports {exc.qualified_name}, "
            "which a codebook never needs"
        ) from None
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a broken file
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CheckpointError(f"{path}: not a valid codebook pickle ({reason})") from None
    return _centroids_of(state, path)


def _centroids_of(state: Any, path: Path) -> np.ndarray:
    """Validate the unpickled asmk codebook state dict and return its centroids."""
    if not isinstance(state, dict) or state.get("type") != "Codebook":
        raise CheckpointError(f"{path}: not an asmk codebook (expected a dict of type 'Codebook')")
    params, inner = state.get("params"), state.get("state")
    if not isinstance(params, dict) or "size" not in params:
        raise CheckpointError(f"{path}: codebook has no params.size")
    if not isinstance(inner, dict) or not isinstance(inner.get("centroids"), np.ndarray):
        raise CheckpointError(f"{path}: codebook has no state.centroids array")
    centroids = inner["centroids"]
    if centroids.ndim != 2 or 0 in centroids.shape:
        raise CheckpointError(f"{path}: codebook centroids have shape {centroids.shape}")
    if not np.issubdtype(centroids.dtype, np.floating):
        raise CheckpointError(f"{path}: codebook centroids have dtype {centroids.dtype}")
    size = _codebook_size(params["size"], path)
    if size != centroids.shape[0]:
        raise CheckpointError(
            f"{path}: codebook params.size {params['size']!r} != {centroids.shape[0]} centroids"
        )
    centroids = np.ascontiguousarray(centroids, dtype=np.float32)
    if not np.isfinite(centroids).all():
        raise CheckpointError(f"{path}: codebook centroids contain non-finite values")
    return centroids


def as_descriptor_array(values: Any, name: str, dim: int | None = None) -> np.ndarray:
    """``values`` (numpy or torch, ``(n, d)``) as finite float32 C-contiguous numpy."""
    if isinstance(values, torch.Tensor):
        values = values.detach().to("cpu", torch.float32).numpy()
    array = np.ascontiguousarray(values, dtype=np.float32)
    if array.ndim != 2 or array.shape[0] == 0:
        raise InputError(f"{name}: expected a non-empty (n, d) array, got shape {array.shape}")
    if dim is not None and array.shape[1] != dim:
        raise InputError(f"{name}: descriptors have d = {array.shape[1]}, the codebook {dim}")
    if not np.isfinite(array).all():
        raise InputError(f"{name}: contains non-finite values")
    return array


def train_codebook(features: np.ndarray, k: int, seed: int, niter: int = 20) -> np.ndarray:
    """Cluster ``features`` into ``k`` centroids with faiss k-means (L2).

    Used for priors without an official codebook (the simulated prior). Deterministic for
    a given ``seed`` and input.

    Args:
        features: ``(M, d)`` training descriptors, ``M >= k``.
        k: number of centroids.
        seed: k-means initialisation seed.
        niter: Lloyd iterations.

    Returns:
        ``(k, d)`` float32 centroids.
    """
    import faiss  # deferred: faiss is an optional dependency (the ``retrieval`` extra)

    features = as_descriptor_array(features, "features")
    if not 1 <= k <= features.shape[0]:
        raise InputError(f"train_codebook: k = {k} must be in [1, {features.shape[0]}] (M)")
    # min_points_per_centroid=1 silences faiss' stderr warning for small training sets.
    kmeans = faiss.Kmeans(
        features.shape[1], k, niter=niter, seed=seed, verbose=False, min_points_per_centroid=1
    )
    kmeans.train(features)
    return np.ascontiguousarray(kmeans.centroids, dtype=np.float32)

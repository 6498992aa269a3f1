"""Keyframes whose large arrays live outside memory until needed (issue 14, bounded memory).

A keyframe's encoding (the simulated prior's is 15.5 MB at 512x384, MASt3R's 3 MB), image
and four pointmaps (2.4 MB each for ``X_hat``, ``X_init``), and an edge's dense matches
(1.3 MB per direction) would make a process grow with the sequence. A
:class:`PagedKeyframe` reads and writes like a :class:`~.keyframes.Keyframe`, but after
:meth:`~PagedKeyframe.evict` its large fields are read back from a :class:`KeyframePages`
the first time something needs them and kept until the next eviction; its light fields
(ids, pose, intrinsics, retrieval features, fused-frame count) always stay. A
:class:`PagedMatches` does the same for an edge's matches.

Two processes page this way: the coordinator reads back from its session store
(:mod:`como3r.store.paging`), an agent's front-end from its own
:class:`KeyframeSpill`, a private folder it writes what it evicts to (:class:`AgentPaging`).
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import tempfile
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from como3r.frontend.keyframes import Keyframe
from como3r.frontend.pairs import DirectedMatches

logger = logging.getLogger(__name__)

#: the pointmap fields of a keyframe, in the session store's ``pointmaps`` column order
POINTMAP_FIELDS = ("X_hat", "C_hat", "X_init", "C_init")
#: the arrays of a keyframe read back together, by group
GROUPS = {"encoding": ("encoding",), "colors": ("colors",), "pointmaps": POINTMAP_FIELDS}
_GROUP_OF = {name: group for group, names in GROUPS.items() for name in names}
#: the fields of a :class:`~como3r.frontend.pairs.DirectedMatches`
MATCH_FIELDS = ("idx", "valid", "q")


class KeyframePages(Protocol):
    """Where a keyframe's paged-out arrays are read back from."""

    def load_keyframe(self, key: int, group: str) -> dict[str, Any]:
        """The current arrays of ``group`` (:data:`GROUPS`) of keyframe ``key``, by name."""


class MatchPages(Protocol):
    """Where an edge's paged-out matches are read back from."""

    def load_edge(self, n: int) -> DirectedMatches:
        """The matches of edge ``n``."""


class _Paged:
    """A large keyframe field: in the keyframe while resident, else read back on access."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name, self.group = name, _GROUP_OF[name]

    def __get__(self, kf: PagedKeyframe | None, owner: type | None = None) -> Any:
        if kf is None:
            return self
        if self.name not in kf._resident:  # fields set since the eviction stay as set
            for name, value in kf._pages.load_keyframe(kf._key, self.group).items():
                kf._resident.setdefault(name, value)
        return kf._resident[self.name]

    def __set__(self, kf: PagedKeyframe, value: Any) -> None:
        kf._resident[self.name] = value
        kf._changed.add(self.group)
        kf._versions[self.group] = kf._versions.get(self.group, 0) + 1


class PagedKeyframe(Keyframe):
    """A keyframe whose encoding, image and pointmaps may live in its pages only (see the
    module docstring); it reads and writes like a :class:`Keyframe`."""

    #: the fields in memory, by name (the others are read from the pages on access)
    _resident: dict[str, Any]

    encoding = _Paged()
    colors = _Paged()
    X_hat = _Paged()
    C_hat = _Paged()
    X_init = _Paged()
    C_init = _Paged()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        object.__setattr__(self, "_resident", {})
        object.__setattr__(self, "_changed", set())  # groups set since the last eviction
        object.__setattr__(self, "_versions", {})  # per group: how many times it was set
        object.__setattr__(self, "_pages", None)
        object.__setattr__(self, "_key", -1)
        super().__init__(*args, **kwargs)

    @classmethod
    def of(cls, kf: Keyframe) -> PagedKeyframe:
        """A paged keyframe holding what ``kf`` holds (the same arrays)."""
        return cls(**{f.name: getattr(kf, f.name) for f in fields(Keyframe)})

    def resident(self, group: str) -> bool:
        """Whether some array of ``group`` is in memory (read back, or set)."""
        return any(name in self._resident for name in GROUPS[group])

    def version(self, group: str) -> int:
        """How many times some field of ``group`` was set (the pointmaps' version tells a
        solve's cached linearizations they are stale)."""
        return self._versions.get(group, 0)

    def changed(self) -> list[str]:
        """The groups some field of which was set since the last eviction (or creation)."""
        return [group for group in GROUPS if group in self._changed]

    def peek(self, *names: str) -> Any:
        """Fields ``names`` (one value for one name, else a tuple); read from the pages
        without keeping them when they are not in memory (a solve over every keyframe must
        not make them all resident), each group read once."""
        groups: dict[str, dict[str, Any]] = {}
        values = []
        for name in names:
            if name in self._resident:
                values.append(self._resident[name])
                continue
            group = _GROUP_OF[name]
            if group not in groups:
                groups[group] = self._pages.load_keyframe(self._key, group)
            values.append(groups[group][name])
        return values[0] if len(names) == 1 else tuple(values)

    def served_by(self, pages: KeyframePages) -> bool:
        """Whether ``pages`` reads this keyframe's paged-out arrays back."""
        return self._pages is pages

    def release(self) -> None:
        """Let go of the arrays read back from the pages; groups set since the eviction
        stay in memory."""
        for name in [n for n in self._resident if _GROUP_OF[n] not in self._changed]:
            del self._resident[name]

    def evict(self, pages: KeyframePages | None, key: int) -> None:
        """Let go of the large arrays; ``pages`` reads them back as keyframe ``key`` (None:
        the pages to read them from are yet to be given)."""
        self._pages, self._key = pages, key
        self._resident.clear()
        self._changed.clear()


class PagedMatches(DirectedMatches):
    """An edge's matches read back from a :class:`MatchPages` the first time they are asked
    for and kept until :meth:`evict`; the match fraction is kept."""

    def __init__(self, pages: MatchPages, n: int, match_fraction: float) -> None:
        for name, value in (
            ("_pages", pages),
            ("_n", n),
            ("_fraction", match_fraction),
            ("_resident", None),
        ):
            object.__setattr__(self, name, value)

    def _matches(self) -> DirectedMatches:
        if self._resident is None:
            object.__setattr__(self, "_resident", self._pages.load_edge(self._n))
        return self._resident

    @property  # type: ignore[override]
    def idx(self) -> Tensor:
        return self._matches().idx

    @property  # type: ignore[override]
    def valid(self) -> Tensor:
        return self._matches().valid

    @property  # type: ignore[override]
    def q(self) -> Tensor:
        return self._matches().q

    @property
    def match_fraction(self) -> float:
        return self._fraction

    def resident(self) -> bool:
        """Whether the matches are in memory."""
        return self._resident is not None

    def evict(self) -> None:
        """Let go of the matches."""
        object.__setattr__(self, "_resident", None)


def read_fields(kf: Keyframe, *names: str) -> Any:
    """Fields ``names`` of ``kf`` (one value for one name, else a tuple); a paged keyframe's
    read back without making it resident (:meth:`PagedKeyframe.peek`)."""
    if isinstance(kf, PagedKeyframe):
        return kf.peek(*names)
    values = tuple(getattr(kf, name) for name in names)
    return values[0] if len(names) == 1 else values


def paged_out(kf: Keyframe) -> bool:
    """Whether ``kf``'s pointmaps live in its pages only (set ones are in memory)."""
    return isinstance(kf, PagedKeyframe) and not kf.resident("pointmaps")


class KeyframeParking:
    """Arrays of paged-out keyframes that their pages cannot take yet, in a private
    :class:`KeyframeSpill` (the coordinator's terminal refinement: the session store takes
    its results in one transaction at its end, so that a store never holds half a cleanup).

    :meth:`park` sets pointmap fields of a paged-out keyframe without making it resident:
    the keyframe is then served by the parking, which reads the parked fields from its spill
    and every other array from the keyframe's former pages. :meth:`put` and :meth:`get` keep
    other per-keyframe arrays (segment labels, snapshots) for the parking's owner.

    Args:
        folder: where the spill folder is made (None: the system's temporary folder).
    """

    def __init__(self, folder: Path | None = None) -> None:
        self._folder = folder
        self._spill: KeyframeSpill | None = None  # made when something is first parked
        self._base: dict[int, KeyframePages] = {}  # key -> the pages it was served by
        self._parked: dict[int, set[str]] = {}  # key -> its parked pointmap fields
        # key -> {field: the parked field holding the same tensor} (X_init while it is
        # X_hat: read back as one tensor, as the store codes it once)
        self._aliases: dict[int, dict[str, str]] = {}
        #: arrays written to the spill (parked fields and :meth:`put`), a counter for tests
        self.writes = 0

    def park(self, kf: PagedKeyframe, values: dict[str, Tensor]) -> None:
        """Set pointmap fields of a paged-out keyframe (:func:`paged_out`), which stays
        paged out.

        Args:
            kf: the keyframe; read back from this parking from now on.
            values: ``(H, W, 3)`` or ``(H, W)`` arrays by field name (:data:`POINTMAP_FIELDS`).
        """
        key = kf._key
        if not kf.served_by(self):
            self._base[key], self._parked[key], self._aliases[key] = kf._pages, set(), {}
        aliases = self._aliases[key]
        for alias, name in list(aliases.items()):
            if name in values and alias not in values:  # it keeps the value it had
                self.put(key, alias, {alias: self.get(key, name)[name]})
                del aliases[alias]
        for name, value in values.items():
            same = next((n for n, v in values.items() if v is value), name)
            if same == name:
                self.put(key, name, {name: value})
                aliases.pop(name, None)
            else:
                aliases[name] = same
            self._parked[key].add(name)
        kf.evict(self, key)

    def put(self, key: int, name: str, values: dict[str, Any]) -> None:
        """Keep the arrays ``values`` as ``name`` of keyframe ``key``."""
        if self._spill is None:
            # uncompressed: what is parked is read back at every solve of the cleanup, and
            # float pointmaps hardly compress (512x384: 3.15 -> 2.82 MB, writes 1.5 -> 92 ms)
            self._spill = KeyframeSpill(self._folder, compress=False)
            logger.debug("parking keyframe arrays in %s", self._spill.folder)
        self._spill.save_keyframe(key, name, values)
        self.writes += len(values)

    def get(self, key: int, name: str) -> dict[str, Any]:
        """The arrays kept as ``name`` of keyframe ``key``."""
        return self._spill.load_keyframe(key, name)

    def load_keyframe(self, key: int, group: str) -> dict[str, Any]:
        """The arrays of ``group`` of a parked keyframe: its parked fields, the rest from
        its former pages (:class:`KeyframePages`), read only where some field is not parked."""
        names = GROUPS[group]
        parked = self._parked[key]
        values = {} if parked >= set(names) else self._base[key].load_keyframe(key, group)
        aliases = self._aliases[key]
        for name in [n for n in names if n in parked and n not in aliases]:
            values[name] = self.get(key, name)[name]
        for name in [n for n in names if n in aliases]:
            values[name] = values[aliases[name]]
        return values


def plain_matches(matches: DirectedMatches | None) -> DirectedMatches | None:
    """``matches`` as a plain :class:`DirectedMatches`, read back if paged out (what leaves
    the process; None stays None)."""
    if isinstance(matches, PagedMatches):
        return DirectedMatches(matches.idx, matches.valid, matches.q)
    return matches


#: a spill folder's name: this prefix, ``pid@host`` of the owning process, a dash and a
#: random suffix (:func:`tempfile.mkdtemp`'s, without dashes)
SPILL_PREFIX = "como3r-spill-"


def _owner() -> str:
    """``pid@host`` of this process (the host name without path separators)."""
    return f"{os.getpid()}@{socket.gethostname().replace(os.sep, '_')}"


def _process_is_gone(pid: int) -> bool:
    """Whether no process ``pid`` runs on this host (one of another user's counts as
    running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


def _remove_orphans(parent: Path) -> None:
    """Remove the spill folders in ``parent`` of this host's processes that are gone: a
    process killed with ``kill -9`` never removes its own. Another host's folders (a shared
    ``session.spill_dir``) are left alone, and so is a folder whose process id was taken
    again: the safe side."""
    host = _owner().split("@", 1)[1]
    for folder in parent.glob(f"{SPILL_PREFIX}*@*-*"):
        pid, _, rest = folder.name[len(SPILL_PREFIX) :].partition("@")
        if (
            folder.is_dir()
            and pid.isdigit()
            and rest.rsplit("-", 1)[0] == host
            and _process_is_gone(int(pid))
        ):
            logger.info("removing the spill folder of a process that is gone: %s", folder)
            shutil.rmtree(folder, ignore_errors=True)


class KeyframeSpill:
    """A process's private folder of numpy arrays (no pickle): keyframe groups
    and edge matches written when they are paged out, read back on demand, removed when
    the spill is garbage-collected or the process exits.

    Tensors come back bit-identical, with their dtype (bfloat16 through its int16 bits) and
    device; an encoding (a dataclass) keeps its tensor fields in the folder and its small
    other fields (ids, shape, scalars) in memory.

    Args:
        parent: the folder to make the spill folder in (None: the system's temporary one).
        compress: deflate the files (smaller, much slower to write and read).
    """

    def __init__(self, parent: Path | None = None, compress: bool = True) -> None:
        self._save_arrays = np.savez_compressed if compress else np.savez
        if parent is not None:
            parent.mkdir(parents=True, exist_ok=True)
        parent = Path(tempfile.gettempdir()) if parent is None else parent
        _remove_orphans(parent)
        self.folder = Path(tempfile.mkdtemp(prefix=f"{SPILL_PREFIX}{_owner()}-", dir=parent))
        # removed with the front-end that owns it, or at the process's exit
        weakref.finalize(self, shutil.rmtree, self.folder, True)
        # per file: how to rebuild each value (kind, dtype or class, device, other fields)
        self._layout: dict[str, dict[str, tuple[Any, ...]]] = {}

    def save_keyframe(self, key: int, group: str, values: dict[str, Any]) -> None:
        """Write the arrays ``values`` (by field name) of ``group`` of keyframe ``key``."""
        self._save(f"kf{key}_{group}", values)

    def load_keyframe(self, key: int, group: str) -> dict[str, Any]:
        """The arrays of ``group`` of keyframe ``key`` as last saved."""
        return self._load(f"kf{key}_{group}")

    def save_edge(self, n: int, matches: DirectedMatches) -> None:
        """Write the matches of edge ``n``."""
        self._save(f"edge{n}", {name: getattr(matches, name) for name in MATCH_FIELDS})

    def load_edge(self, n: int) -> DirectedMatches:
        """The matches of edge ``n``."""
        return DirectedMatches(**self._load(f"edge{n}"))

    def _save(self, name: str, values: dict[str, Any]) -> None:
        arrays: dict[str, np.ndarray] = {}
        layout = {}
        for field_name, value in values.items():
            if is_dataclass(value):
                tensors = {f.name: getattr(value, f.name) for f in fields(value)}
                others = {k: v for k, v in tensors.items() if not isinstance(v, Tensor)}
                for k in others:
                    del tensors[k]
                for k, tensor in tensors.items():
                    arrays[f"{field_name}.{k}"] = _numpy(tensor)
                layout[field_name] = (
                    "dataclass",
                    type(value),
                    others,
                    {k: (t.dtype, t.device) for k, t in tensors.items()},
                )
            elif isinstance(value, Tensor):
                arrays[field_name] = _numpy(value)
                layout[field_name] = ("tensor", value.dtype, value.device)
            else:
                arrays[field_name] = np.asarray(value)
                layout[field_name] = ("array",)
        self._save_arrays(self.folder / f"{name}.npz", **arrays)
        self._layout[name] = layout

    def _load(self, name: str) -> dict[str, Any]:
        with np.load(self.folder / f"{name}.npz", allow_pickle=False) as data:
            values: dict[str, Any] = {}
            for field_name, layout in self._layout[name].items():
                if layout[0] == "dataclass":
                    cls, others, tensors = layout[1], layout[2], layout[3]
                    values[field_name] = cls(
                        **others,
                        **{
                            k: _tensor(data[f"{field_name}.{k}"], dtype, device)
                            for k, (dtype, device) in tensors.items()
                        },
                    )
                elif layout[0] == "tensor":
                    values[field_name] = _tensor(data[field_name], layout[1], layout[2])
                else:
                    values[field_name] = data[field_name]
        return values


def _numpy(tensor: Tensor) -> np.ndarray:
    tensor = tensor.detach().cpu()
    return (tensor.view(torch.int16) if tensor.dtype == torch.bfloat16 else tensor).numpy()


def _tensor(array: np.ndarray, dtype: torch.dtype, device: torch.device) -> Tensor:
    tensor = torch.from_numpy(array)
    return (tensor.view(dtype) if dtype == torch.bfloat16 else tensor).to(device)


@dataclass(frozen=True)
class SolvePoints:
    """What a solve reads of a keyframe (:func:`~.graph.build_factors`).

    Attributes:
        X_hat: ``(H, W, 3)`` canonical pointmap in the keyframe's camera frame.
        K: ``(3, 3)`` intrinsics, None in an uncalibrated run.
    """

    X_hat: Tensor
    K: Tensor | None


def solve_points(keyframe: Callable[[int], Keyframe]) -> Callable[[int], SolvePoints]:
    """What one solve reads of each keyframe (:class:`SolvePoints`), read back once per
    keyframe and kept by the solve only: a paged-out keyframe stays paged out
    (:func:`read_fields`), so a solve over a whole map holds one pointmap per keyframe while
    it runs and none after it.

    Args:
        keyframe: maps a solve's keyframe key to the keyframe.
    """
    cache: dict[int, SolvePoints] = {}

    def points(k: int) -> SolvePoints:
        if k not in cache:
            kf = keyframe(k)
            cache[k] = SolvePoints(read_fields(kf, "X_hat"), kf.K)
        return cache[k]

    return points


class AgentPaging:
    """An agent front-end's keyframes and edges outside its working set, paged out to a
    :class:`KeyframeSpill`.

    The working set is the newest ``resident`` keyframes: tracking fuses into the newest,
    linking decodes it with its predecessor. Whatever else a step needs (loop-closure and
    relocalization candidates, the pointmaps and matches of a local solve over every edge,
    the keyframes a coordinator's update moves, the outputs) is read back while the step
    runs and let go by the next :meth:`page_out`, so the results do not depend on
    ``resident``; only memory and time do.

    Args:
        resident: keyframes kept whole in memory.
        folder: where the spill folder is made (None: the system's temporary folder).
    """

    def __init__(self, resident: int, folder: Path | None = None) -> None:
        self.resident = resident
        self._folder = folder
        self._spill: KeyframeSpill | None = None  # made when something is first paged out

    def page_out(self, keyframes: Sequence[PagedKeyframe], edges: list[Any]) -> None:
        """Write what changed of the keyframes outside the working set and let go of their
        large arrays; edges between two such keyframes keep their match fraction only.

        Args:
            keyframes: the agent's keyframes in id order.
            edges: the agent's edges (:class:`~.graph.Edge`), replaced in place by edges
                with :class:`PagedMatches`.
        """
        first_kept = len(keyframes) - self.resident
        if first_kept <= 0:
            return
        spill = self._spill_folder()
        for kf in keyframes[:first_kept]:
            for group in kf.changed():
                spill.save_keyframe(
                    kf.kf_id, group, {name: getattr(kf, name) for name in GROUPS[group]}
                )
            if kf._resident or kf._pages is None:
                kf.evict(spill, kf.kf_id)
        for n, edge in enumerate(edges):
            if isinstance(edge.matches, PagedMatches):
                edge.matches.evict()
            elif edge.i < first_kept and edge.j < first_kept:
                spill.save_edge(n, edge.matches)
                edges[n] = replace(
                    edge, matches=PagedMatches(spill, n, edge.matches.match_fraction)
                )

    def _spill_folder(self) -> KeyframeSpill:
        if self._spill is None:
            self._spill = KeyframeSpill(self._folder)
            logger.debug("paging keyframes out to %s", self._spill.folder)
        return self._spill

"""A link of the coordinator's global graph (:mod:`.global_graph`): two keyframes and their
dense matches in both directions, which give its two directed factor edges."""

from __future__ import annotations

from dataclasses import dataclass

from como3r.frontend.graph import Edge
from como3r.frontend.pairs import PairLink


@dataclass(frozen=True)
class GraphLink:
    """An undirected link between two keyframes, with its matches in both directions.

    Attributes:
        i: global index of endpoint i.
        j: global index of endpoint j.
        kind: ``"sequential"``, ``"loop"`` or ``"inter"``.
        link: ``link.ij`` matches every pixel of j in i, ``link.ji`` every pixel of i in j.
        similarity: retrieval similarity (inter links only).
    """

    i: int
    j: int
    kind: str
    link: PairLink
    similarity: float | None = None

    def edges(self) -> tuple[Edge, Edge]:
        """The two directed factor edges of the link."""
        return Edge(self.i, self.j, self.link.ij, self.kind), Edge(
            self.j, self.i, self.link.ji, self.kind
        )

"""coordination/census.py: a coordinator's tensors and arrays summed by owner, each storage
once, without reading back what is paged out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from como3r.coordination.census import census
from como3r.frontend.paging import PagedKeyframe


@dataclass
class _Part:
    values: dict
    items: list


class _Owner:
    def __init__(self) -> None:
        shared = torch.zeros(1000)  # 4000 bytes
        self.first = _Part({"a": shared, "b": shared[10:20]}, [])
        self.second = _Part({}, [shared.view(10, 100), np.zeros(50), torch.zeros(25)])
        self.prior = torch.zeros(10**6)  # not the map's: not counted
        self.loop = self  # cycles end


def test_each_storage_is_counted_once_by_its_first_owner() -> None:
    held = census(_Owner())
    # the shared storage once (three views of it), the numpy buffer, the small tensor
    assert sum(held.values()) == 4000 + 400 + 100
    assert set(held) <= {"first.values.a", "first.values.b", "second.items"}


def test_a_paged_out_keyframe_is_not_read_back_by_counting_it() -> None:
    class Pages:
        reads = 0

        def load_keyframe(self, key: int, group: str) -> dict:
            Pages.reads += 1
            raise AssertionError("counting read a paged-out array back")

    kf = PagedKeyframe(
        kf_id=0,
        frame_index=0,
        timestamp=0.0,
        encoding=None,
        T_WC=torch.zeros(8),
        X_hat=torch.zeros(4, 4, 3),
        C_hat=torch.ones(4, 4),
        X_init=torch.zeros(4, 4, 3),
        C_init=torch.ones(4, 4),
        colors=np.zeros((4, 4, 3), np.uint8),
        retrieval=None,
        K=None,
    )

    class Holder:
        def __init__(self) -> None:
            self.keyframes = [kf]

    resident = sum(census(Holder()).values())
    assert resident >= 2 * 4 * 4 * 3 * 4  # both pointmaps
    kf.evict(Pages(), 0)
    assert sum(census(Holder()).values()) == 32  # the pose alone stays
    assert Pages.reads == 0

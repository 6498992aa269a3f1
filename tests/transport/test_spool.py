"""An agent's unacknowledged messages: in memory up to a limit, then on disk; put again from
the oldest after a reconnect; forgotten once stored."""

from __future__ import annotations

from como3r.transport.spool import Spool


def test_past_its_memory_limit_the_spool_spills_to_disk_and_loses_nothing(tmp_path) -> None:
    spool = Spool(memory_bytes=250, spill_dir=tmp_path, label="agent-3")
    payloads = [bytes([n]) * 100 for n in range(6)]
    assert [spool.append(f"k/{n}", p) for n, p in enumerate(payloads)] == list(range(6))
    assert spool.in_memory == 200 and spool.spilled == 4
    [folder] = tmp_path.iterdir()
    assert folder.name.startswith("como3r-agent-3-") and len(list(folder.iterdir())) == 4
    taken = [spool.take() for _ in range(4)]
    assert taken == [(n, f"k/{n}", payloads[n]) for n in range(4)]
    spool.acknowledge(2)  # the coordinator stored 0..2
    assert len(spool) == 3 and spool.in_memory == 0 and len(list(folder.iterdir())) == 3
    assert spool.rewind() == 3  # it came back: everything not stored, oldest first
    assert [spool.take()[0] for _ in range(3)] == [3, 4, 5] and not spool.has_next()
    spool.append("k/6", b"x" * 10)  # room in memory again
    assert spool.in_memory == 10 and spool.spilled == 4
    spool.acknowledge(6)
    assert len(spool) == 0 and list(folder.iterdir()) == []
    spool.close()
    assert not folder.exists()


def test_an_acknowledgement_behind_the_cursor_keeps_the_rest_in_order() -> None:
    spool = Spool()
    for n in range(3):
        spool.append("k", bytes([n]))
    assert spool.take()[0] == 0
    spool.acknowledge(1)  # acknowledged past what was taken (a re-send stored earlier)
    assert spool.take() == (2, "k", b"\x02") and len(spool) == 1

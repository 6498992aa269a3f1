"""An agent process builds the prior its task names, precision included."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

from como3r.config import Config, apply_overrides
from como3r.data.synth import synthesize
from como3r.prior.mast3r.testing import tiny_network, write_checkpoint
from como3r.runtime.agent_events import RuntimeOptions
from como3r.runtime.agent_worker import AgentWorker, prior_fields, prior_spec
from como3r.runtime.pipeline import PriorSpec
from como3r.runtime.processes import _Runtime
from como3r.transport.codec import decode, encode
from como3r.transport.messages import AgentTask, KeyframeMessage


class _TaskRecorder:
    """A hub that only keeps the tasks it is given."""

    name = "recorder"

    def start(self, tasks: Sequence[AgentTask], rejoin: Any = None) -> None:
        self.tasks = list(tasks)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_the_task_carries_the_precision_to_the_agent_prior(tmp_path, precision) -> None:
    (tmp_path / "scene").mkdir()
    synthesize(
        tmp_path / "scene",
        agents=1,
        seed=0,
        overlap=0.5,
        frames=4,
        preset="default",
        width=64,
        height=48,
        progress=None,
    )
    ckpt = write_checkpoint(tmp_path / "tiny.pth", tiny_network(seed=0))
    spec = PriorSpec("mast3r", weights=ckpt, precision=precision)
    assert prior_spec(prior_fields(spec)) == spec
    config = apply_overrides(Config(), ["input.long_side=64"])
    hub = _TaskRecorder()
    runtime = _Runtime(hub, [4], config, spec, RuntimeOptions(), None)
    runtime.start([tmp_path / "scene" / "agent_0"], spec)
    task = decode(encode(hub.tasks[0]), expected=AgentTask)  # as it crosses the wire
    worker = AgentWorker(task, channel=None)
    assert worker.prior.describe()["precision"] == precision
    assert runtime.prior.describe()["precision"] == precision  # the coordinator's own


def test_a_task_without_precision_gets_the_default() -> None:
    assert prior_spec({"name": "simulated", "device": "cpu"}) == PriorSpec("simulated")
    assert isinstance(prior_spec({"name": "mast3r", "weights": "w.pth"}).weights, Path)


class _Sent:
    """An agent link that keeps what the agent sends."""

    def __init__(self) -> None:
        self.messages: list[Any] = []

    def send(self, message: Any) -> None:
        self.messages.append(message)

    def poll(self, timeout: float) -> bool:
        return False  # no pose updates come back


@pytest.mark.slow  # a whole agent run: 10-30 s on 2 busy cores
@pytest.mark.parametrize("prior", ["mast3r", "simulated"])
def test_the_task_says_whether_keyframes_carry_their_encoding(tmp_path, prior) -> None:
    """MASt3R's coordinator encodes the keyframes' colours again: its agents send no
    encodings; the simulated prior's cannot (ground truth): its agents send them."""
    (tmp_path / "scene").mkdir()
    synthesize(
        tmp_path / "scene",
        agents=1,
        seed=0,
        overlap=0.5,
        frames=4,
        preset="default",
        width=64,
        height=48,
        progress=None,
    )
    ckpt = write_checkpoint(tmp_path / "tiny.pth", tiny_network(seed=0))
    spec = PriorSpec(prior, weights=ckpt if prior == "mast3r" else None)
    config = apply_overrides(Config(), ["input.long_side=64"])
    hub = _TaskRecorder()
    runtime = _Runtime(hub, [4], config, spec, RuntimeOptions(), None)
    runtime.start([tmp_path / "scene" / "agent_0"], spec)
    task = decode(encode(hub.tasks[0]), expected=AgentTask)
    assert task.send_encoding is (prior == "simulated")
    sent = _Sent()
    worker = AgentWorker(task, channel=sent)
    worker.run()
    packets = [m.packet for m in sent.messages if isinstance(m, KeyframeMessage)]
    assert packets and all((p.encoding is not None) is task.send_encoding for p in packets)
    assert all(p.colors.shape[:2] == p.X_hat.shape[:2] for p in packets)


def test_an_agent_process_imports_no_back_end() -> None:
    """An agent's process (spawned: its entry module; ``como3r agent``: the network runtime)
    needs no coordinator, back-end or scikit-image: importing them costs it ~0.5 s CPU."""
    probe = (
        "import sys, como3r.runtime.agent_worker, como3r.runtime.network; "
        "print(sorted(m for m in sys.modules if m.startswith(('como3r.coordination', "
        "'como3r.backend', 'skimage'))))"
    )
    found = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    )
    assert found.stdout.strip() == "[]", found.stdout

"""Radio links: a coordinator and its agents on capped and cut links (not a test).

Each agent and the coordinator run as ``como3r agent`` / ``como3r coordinator`` processes in
network namespaces of their own, each agent joined to the coordinator by a veth pair
(``10.77.N.4a+1`` on the coordinator's side, ``.4a+2`` on the agent's, a /30 per agent),
both ends shaped by ``tc``'s token bucket (``tbf``: a cap in each direction, as a
full-duplex radio link). A *cut* takes agent 0's link down (``ip link set down``) once the
coordinator has acknowledged its first message (the agent is tracking), for the given
seconds, and up again. The reference is the
same team on loopback in the root namespace (no cap). Everything made here (namespaces,
veths, named ``c3l<tag>...``) is deleted at the end, whatever happens; traffic goes only
over them or loopback.

Per run it prints, from the tbf counters of each agent's link (sampled every 0.5 s, Zenoh's
and TCP's overhead included) and the run's ``metrics.json``:

* ``up kB``/``down kB``: bytes each robot sent to / got from the coordinator (agent 0, 1);
* ``peak/cap``: the highest up rate of a robot over 2 s, over the cap;
* ``stall s``: per robot, the longest time between two acknowledgements the coordinator
  sent it, from its first to its last (what a cut costs, and any wait behind other traffic
  or for another robot's keyframes);
* ``caught up s``: link up to the cut agent logging that the coordinator has stored every
  message it made before the coordinator came back (``-``: no cut);
* ``away``: messages the cut agent made while it saw no coordinator (tracking on);
* ``lost F/KF``: frames processed by an agent but not reported to the coordinator, and
  keyframes an agent made that are not in the outputs (goal: 0/0);
* ``ack ms``: the longest an acknowledgement took from the coordinator's namespace to a
  robot's, while that robot's keyframes filled the other direction (the acknowledgements
  that reached the probes, some 10 a robot);
* ``ATE mm`` and ``vs loop``: merged ATE RMSE, and its change from the loopback run.

The acknowledgements are those a probe sees: a Zenoh session in each agent's namespace,
subscribed to that agent's acknowledgements over its own connection on the same link.

Needs root, ``ip`` and ``tc`` (``netem`` is not needed). Run::

    python benchmarks/links.py --frames 16 --side 128 --caps 1 5 20 --cuts 10 120
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

PORT = 7447
LIMIT_S = 900  # no process of a run outlives this
SAMPLE_S = 0.5
LATENCY_MS = 100  # the most a packet waits in a link's queue at the cap


def namespaces_unavailable() -> str | None:
    """Why this machine cannot make the namespaces, or None if it can."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            return f"no `{tool}` command"
    probe = f"c3l{uuid.uuid4().hex[:6]}p"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"ip netns add failed: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip()}")


def _tc(*args: str) -> None:
    done = subprocess.run(["tc", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"tc {' '.join(args)}: {done.stderr.strip()}")


class Radio:
    """The namespaces and veth links of one team: ``coord`` and ``agent<a>``; deleted by
    :meth:`close` (also what a failed setup made).

    Args:
        agents: how many agents.
        cap_mbit: the cap of each direction of each link (None: none).
    """

    def __init__(self, agents: int, cap_mbit: float | None) -> None:
        self.tag = uuid.uuid4().hex[:5]
        self.net = 100 + os.getpid() % 150  # 10.77.<net>.x: our own namespaces only
        self.coord = f"c3l{self.tag}c"
        self.agents = [f"c3l{self.tag}a{a}" for a in range(agents)]
        self.made: list[str] = []
        try:
            for ns in (self.coord, *self.agents):
                _ip("netns", "add", ns)
                self.made.append(ns)
                _ip("-n", ns, "link", "set", "lo", "up")
            for a, ns in enumerate(self.agents):
                here, there = self.coord_dev(a), self.agent_dev(a)
                _ip(
                    "-n",
                    self.coord,
                    "link",
                    "add",
                    here,
                    "type",
                    "veth",
                    "peer",
                    "name",
                    there,
                    "netns",
                    ns,
                )
                _ip("-n", self.coord, "addr", "add", f"{self.coord_addr(a)}/30", "dev", here)
                _ip("-n", ns, "addr", "add", f"{self.agent_addr(a)}/30", "dev", there)
                for name, dev in ((self.coord, here), (ns, there)):
                    _ip("-n", name, "link", "set", dev, "up")
                    if cap_mbit is not None:
                        rate = int(cap_mbit * 1e6)
                        burst = max(4 * 1514, rate // 8 // 50)  # 20 ms at the cap
                        _tc(
                            "-n",
                            name,
                            "qdisc",
                            "add",
                            "dev",
                            dev,
                            "root",
                            "tbf",
                            "rate",
                            f"{rate}bit",
                            "burst",
                            str(burst),
                            "latency",
                            f"{LATENCY_MS}ms",
                        )
        except BaseException:
            self.close()
            raise

    def coord_dev(self, a: int) -> str:
        return f"c3l{self.tag}c{a}"

    def agent_dev(self, a: int) -> str:
        return f"c3l{self.tag}a{a}"

    def coord_addr(self, a: int) -> str:
        return f"10.77.{self.net}.{4 * a + 1}"

    def agent_addr(self, a: int) -> str:
        return f"10.77.{self.net}.{4 * a + 2}"

    def link(self, a: int, up: bool) -> None:
        _ip("-n", self.coord, "link", "set", self.coord_dev(a), "up" if up else "down")

    def sent_bytes(self, a: int) -> tuple[int, int]:
        """Bytes agent ``a`` has sent up and the coordinator down its link so far."""

        def tx(ns: str, dev: str) -> int:
            out = subprocess.run(
                ["ip", "-n", ns, "-s", "-j", "link", "show", "dev", dev],
                capture_output=True,
                text=True,
            ).stdout
            return int(json.loads(out)[0]["stats64"]["tx"]["bytes"]) if out else 0

        return tx(self.agents[a], self.agent_dev(a)), tx(self.coord, self.coord_dev(a))

    def close(self) -> None:
        for ns in reversed(self.made):  # a namespace takes its veth ends with it
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self.made.clear()


class Process:
    """A child process whose output lines are kept with the time each arrived (and
    written to ``log``)."""

    def __init__(self, argv: list[str], log: Path) -> None:
        self.log = log
        self.lines: list[tuple[float, str]] = []
        self.popen = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=os.environ.copy()
        )
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        with open(self.log, "w") as log:
            for line in self.popen.stdout:
                self.lines.append((time.monotonic(), line.rstrip("\n")))
                log.write(line)
                log.flush()

    def first(self, fragment: str, after: float = 0.0) -> float | None:
        return next((t for t, line in list(self.lines) if t >= after and fragment in line), None)

    def wait(self, timeout: float) -> int:
        code = self.popen.wait(timeout)
        self.reader.join(5)
        return code

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()


PROBE = """
import struct, sys, time, json, zenoh
config = zenoh.Config.from_json5("{ transport: { shared_memory: { enabled: false } } }")
config.insert_json5("mode", '"peer"')
config.insert_json5("scouting/multicast/enabled", "false")
config.insert_json5("scouting/gossip/enabled", "false")
config.insert_json5("listen/endpoints", "[]")
config.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
session = zenoh.open(config)
def on_ack(sample):
    inc, seq = struct.unpack("<QQ", sample.payload.to_bytes())
    agent = str(sample.key_expr).rsplit("/", 2)[-2]
    print(f"ack {time.monotonic():.4f} {agent} {seq}", flush=True)
sub = session.declare_subscriber(sys.argv[2], on_ack)
print("probe ready", flush=True)
time.sleep(float(sys.argv[3]))  # killed once the run is over, else gone by itself
"""


@dataclass
class Run:
    """One team's run: its processes, traffic samples and output folder."""

    name: str
    cap_mbit: float | None
    cut_s: float | None
    out: Path
    processes: dict[str, Process] = field(default_factory=dict)
    samples: list[tuple[float, list[tuple[int, int]]]] = field(default_factory=list)
    cut_at: float | None = None
    up_at: float | None = None


def _como3r(*args: str) -> list[str]:
    return [sys.executable, "-m", "como3r.cli", *args]


def run_team(
    name: str,
    scene: Path,
    work: Path,
    side: int,
    agents: int,
    cap_mbit: float | None,
    cut_s: float | None,
    loopback: bool,
    lease_s: float | None = None,
) -> Run:
    """One run of a coordinator and ``agents`` agents on ``scene``; in namespaces unless
    ``loopback``. ``lease_s``: the Zenoh lease every process announces (None: Zenoh's 10 s);
    a cut longer than it ends the links on both sides."""
    run = Run(name, cap_mbit, cut_s, work / name)
    logs = work / f"{name}.logs"
    logs.mkdir(parents=True, exist_ok=True)
    session = f"links{uuid.uuid4().hex[:8]}"
    # as on separate machines: Zenoh would otherwise hand large messages over in shared
    # memory (one host, one /dev/shm) and only their handles would cross the link
    zenoh_config = logs / "zenoh.json5"
    lease = "" if lease_s is None else f", link: {{ tx: {{ lease: {lease_s * 1000:.0f} }} }}"
    zenoh_config.write_text(f"{{ transport: {{ shared_memory: {{ enabled: false }}{lease} }} }}")
    radio = None if loopback else Radio(agents, cap_mbit)
    try:

        def inside(ns: str | None, argv: list[str]) -> list[str]:
            return argv if ns is None else ["ip", "netns", "exec", ns, *argv]

        port = PORT if radio is not None else _free_port()
        coord_ns = radio.coord if radio is not None else None
        gts = [arg for a in range(agents) for arg in ("--gt", str(scene / f"agent_{a}"))]
        run.processes["coordinator"] = Process(
            inside(
                coord_ns,
                _como3r(
                    "coordinator",
                    "--listen",
                    f"tcp/0.0.0.0:{port}",
                    "--out",
                    str(run.out),
                    "--agents",
                    str(agents),
                    "--prior",
                    "simulated",
                    "--set",
                    f"input.long_side={side}",
                    "--session",
                    session,
                    "--away-timeout",
                    "600",
                    "--zenoh-config",
                    str(zenoh_config),
                    "--quiet",
                    *gts,
                ),
            ),
            logs / "coordinator.log",
        )
        # the acknowledgements as sent (beside the coordinator) and as they arrive (beside
        # each agent): their delay across the link
        run.processes["probe"] = Process(
            inside(
                coord_ns,
                [
                    sys.executable,
                    "-c",
                    PROBE,
                    f"tcp/127.0.0.1:{port}",
                    f"como3r/{session}/agent/*/ack",
                    str(LIMIT_S),
                ],
            ),
            logs / "probe.log",
        )
        for a in range(agents):
            ns = radio.agents[a] if radio is not None else None
            where = radio.coord_addr(a) if radio is not None else "127.0.0.1"
            endpoint = f"tcp/{where}:{port}"
            run.processes[f"probe{a}"] = Process(
                inside(
                    ns,
                    [
                        sys.executable,
                        "-c",
                        PROBE,
                        endpoint,
                        f"como3r/{session}/agent/{a}/ack",
                        str(LIMIT_S),
                    ],
                ),
                logs / f"probe{a}.log",
            )
            run.processes[f"agent{a}"] = Process(
                inside(
                    ns,
                    _como3r(
                        "agent",
                        "--connect",
                        endpoint,
                        "--id",
                        str(a),
                        str(scene / f"agent_{a}"),
                        "--prior",
                        "simulated",
                        "--threads",
                        "1",
                        "--session",
                        session,
                        "--zenoh-config",
                        str(zenoh_config),
                    ),
                ),
                logs / f"agent{a}.log",
            )
        _watch(run, radio, agents)
        code = _wait(run, "coordinator", LIMIT_S)
        if code != 0:
            raise RuntimeError(f"{name}: the coordinator failed (exit {code}){_tails(run)}")
        for a in range(agents):
            _wait(run, f"agent{a}", 60)
        return run
    finally:
        for process in run.processes.values():
            process.kill()
        if radio is not None:
            radio.close()


def _wait(run: Run, name: str, timeout: float) -> int:
    """The exit code of ``run``'s process ``name``; a RuntimeError with every process's last
    lines if it is still running after ``timeout`` seconds."""
    try:
        return run.processes[name].wait(timeout)
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"{run.name}: {name} still runs {timeout:g} s on{_tails(run)}") from None


def _tails(run: Run, lines: int = 15) -> str:
    """The last ``lines`` lines of each of ``run``'s processes, to say why it failed."""
    return "".join(
        f"\n--- {name} ({process.log}):\n" + "\n".join(line for _, line in process.lines[-lines:])
        for name, process in run.processes.items()
        if not name.startswith("probe")
    )


def _watch(run: Run, radio: Radio | None, agents: int) -> None:
    """Sample the links until the coordinator ends; cut agent 0's link once the
    coordinator has acknowledged its first message (it has its task and is tracking)."""
    coordinator, deadline = run.processes["coordinator"], time.monotonic() + LIMIT_S
    while coordinator.popen.poll() is None and time.monotonic() < deadline:
        now = time.monotonic()
        if radio is not None:
            run.samples.append((now, [radio.sent_bytes(a) for a in range(agents)]))
            if run.cut_s is not None and run.cut_at is None and _acks(run, 0):
                radio.link(0, up=False)
                run.cut_at = time.monotonic()
            if run.cut_at is not None and run.up_at is None and now - run.cut_at >= run.cut_s:
                radio.link(0, up=True)
                run.up_at = time.monotonic()
        time.sleep(SAMPLE_S)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Row:
    name: str
    up_kb: list[float]
    down_kb: list[float]
    peak_over_cap: float | None
    stall_s: list[float]
    caught_up_s: float | None
    made_away: int
    lost_frames: int
    lost_keyframes: int
    ate_mm: float
    ack_ms: float
    acks: int


def summarize(run: Run, agents: int) -> Row:
    """The table row of ``run`` (see the module docstring)."""
    metrics = json.loads((run.out / "metrics.json").read_text())
    entries = metrics["runtime"]["agents"]
    lost_frames = sum(e["frames_expected"] - e["frames_done"] for e in entries)
    lost_keyframes = sum(
        max(0, metrics["agents"][a]["keyframes"] - e["keyframes_received"])
        for a, e in enumerate(entries)
    )
    up = [s[1][a][0] / 1e3 for a in range(agents) for s in run.samples[-1:]]  # [] on loopback
    down = [s[1][a][1] / 1e3 for a in range(agents) for s in run.samples[-1:]]
    peak = None
    if run.cap_mbit is not None and run.samples:
        rates = []
        for (t0, b0), (t1, b1) in zip(run.samples, run.samples[4:]):  # ~2 s windows
            rates += [(b1[a][0] - b0[a][0]) * 8 / (t1 - t0) for a in range(agents)]
        peak = max(rates, default=0.0) / (run.cap_mbit * 1e6)
    acks = {a: _acks(run, a) for a in range(agents)}
    stall = [
        max((t1 - t0 for (t0, _), (t1, _) in zip(times, times[1:])), default=0.0)
        for times in acks.values()
    ]
    delays = [d for a in range(agents) for d in _ack_delays(run, a)]
    made_away = sum(
        int(n)
        for _, line in run.processes["agent0"].lines
        for n in re.findall(r"(\d+) of them made while it was away", line)
    )
    caught = None
    if run.up_at is not None:
        done = run.processes["agent0"].first("caught up", after=run.up_at)
        caught = done - run.up_at if done is not None else float("nan")
    return Row(
        run.name,
        up,
        down,
        peak,
        stall,
        caught,
        made_away,
        lost_frames,
        lost_keyframes,
        metrics["ate"]["merged"]["ate"]["rmse"] * 1e3,
        max(delays) * 1e3 if delays else float("nan"),
        len(delays),
    )


def _acks(run: Run, a: int, probe: str | None = None) -> list[tuple[float, int]]:
    """``(time, seq)`` of each acknowledgement to agent ``a`` that ``probe`` saw (its
    own probe by default)."""
    out = []
    for _, line in run.processes[probe or f"probe{a}"].lines:
        if line.startswith("ack "):
            _, t, agent, seq = line.split()
            if int(agent) == a:
                out.append((float(t), int(seq)))
    return out


def _ack_delays(run: Run, a: int) -> list[float]:
    """Seconds from each acknowledgement to agent ``a`` leaving the coordinator to its
    arrival in ``a``'s namespace (but those sent while ``a``'s link was cut)."""
    sent: dict[int, float] = {}
    for t, seq in _acks(run, a, "probe"):
        sent.setdefault(seq, t)
    arrived: dict[int, float] = {}
    for t, seq in _acks(run, a):
        arrived.setdefault(seq, t)
    cut = (run.cut_at, run.up_at) if a == 0 and run.cut_at is not None else None
    return [
        arrived[seq] - t
        for seq, t in sent.items()
        if seq in arrived and not (cut is not None and cut[0] <= t <= (cut[1] or math.inf))
    ]  # sent into the cut


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=16, help="frames per agent")
    parser.add_argument("--side", type=int, default=128, help="image long side (pixels)")
    parser.add_argument("--agents", type=int, default=2)
    parser.add_argument(
        "--caps", type=float, nargs="*", default=[1, 5, 20], help="link caps to run, Mbit/s"
    )
    parser.add_argument(
        "--cuts",
        type=float,
        nargs="*",
        default=[10, 120],
        help="cuts of agent 0's link to run, seconds (each at --cut-cap)",
    )
    parser.add_argument("--cut-cap", type=float, default=5, help="the cap of the cut runs")
    parser.add_argument(
        "--work",
        type=Path,
        default=None,
        help="folder for scenes, runs and logs (default: a temporary one)",
    )
    args = parser.parse_args(argv)
    # a kill (timeout) unwinds like Ctrl-C: the namespaces and processes go with it
    signal.signal(signal.SIGTERM, _interrupt)
    why = namespaces_unavailable()
    if why is not None:
        print(f"skipped: {why}")
        return 1
    work = args.work or Path(tempfile.mkdtemp(prefix="como3r-links-"))
    work.mkdir(parents=True, exist_ok=True)
    from como3r.data.synth import synthesize

    scene = work / "scene"
    if not (scene / "agent_0").exists():
        scene.mkdir(exist_ok=True)
        synthesize(
            scene,
            agents=args.agents,
            seed=0,
            overlap=0.5,
            frames=args.frames,
            preset="default",
            width=args.side,
            height=args.side * 3 // 4,
            progress=None,
        )
    cases = [("loopback", None, None, True)]
    cases += [(f"cap {c:g}", c, None, False) for c in args.caps]
    cases += [(f"cut {s:g}s @{args.cut_cap:g}", args.cut_cap, s, False) for s in args.cuts]
    rows = []
    for name, cap, cut, loopback in cases:
        run = run_team(
            name.replace(" ", "_").replace("@", ""),
            scene,
            work,
            args.side,
            args.agents,
            cap,
            cut,
            loopback,
        )
        rows.append(summarize(run, args.agents))
        rows[-1].name = name
        (work / "links.json").write_text(
            json.dumps([dataclasses.asdict(r) for r in rows], indent=1)
        )
        print(f"{name}: done", flush=True)
    _print(rows)
    return 0


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _print(rows: list[Row]) -> None:
    reference = rows[0].ate_mm
    head = (
        f"{'run':<14} {'up kB':>14} {'down kB':>12} {'peak/cap':>8} {'stall s':>11} "
        f"{'caught s':>8} {'away':>4} {'ack ms':>6} {'lost F/KF':>9} {'ATE mm':>7} {'vs loop':>7}"
    )
    print(head)
    for r in rows:
        peak = f"{r.peak_over_cap:.2f}" if r.peak_over_cap is not None else "-"
        caught = f"{r.caught_up_s:.1f}" if r.caught_up_s is not None else "-"
        change = (r.ate_mm - reference) / reference * 100
        print(
            f"{r.name:<14} {'/'.join(f'{x:.0f}' for x in r.up_kb) or '-':>14} "
            f"{'/'.join(f'{x:.0f}' for x in r.down_kb) or '-':>12} {peak:>8} "
            f"{'/'.join(f'{x:.1f}' for x in r.stall_s):>11} {caught:>8} {r.made_away:>4} {r.ack_ms:>6.1f} "
            f"{f'{r.lost_frames}/{r.lost_keyframes}':>9} "
            f"{r.ate_mm:>7.2f} "
            f"{change:>+6.1f}%"
        )


if __name__ == "__main__":
    sys.exit(main())

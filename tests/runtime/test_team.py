"""A team that admits only the team (transport/team.py, team_access.py, ``como3r team``,
``--team``): the authority and member folders, then on loopback TLS: members are admitted;
a peer without a certificate, with another team's, with an expired or a revoked one changes
nothing; a valid member writing under another member's id changes nothing and is logged; a
team run merges as before; without --team a networked command says once that the network
is open."""

from __future__ import annotations

import datetime
import json
import logging
import socket
import stat
import struct
import threading
import time
import uuid
from pathlib import Path

import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.cli_network import OPEN_NETWORK
from como3r.config import Config, config_to_dict
from como3r.decentralized.messages import EncodingRequest, RobotHello
from como3r.decentralized.schedule import Schedule
from como3r.decentralized.zenoh_robot import RobotKeys, ZenohRobotLink
from como3r.errors import InputError
from como3r.transport import codec
from como3r.transport import team as teams
from como3r.transport import team_access as access
from como3r.transport.links import Received, Rejected
from como3r.transport.messages import AgentStarted, AgentTask
from como3r.transport.zenoh_agent import ZenohAgentLink
from como3r.transport.zenoh_hub import ZenohHub
from como3r.transport.zenoh_protocol import Keys, ZenohOptions, open_session

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

zenoh = pytest.importorskip("zenoh")

#: what a user would pass for a tiny run: 64x48 images
SIZE = ["--set", "input.long_side=64"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


WAIT_S = 30.0  # no wait of a test below lasts longer
QUIET_S = 1.5  # how long "nothing arrives" is watched


@pytest.fixture(scope="module")
def crew(tmp_path_factory) -> Path:
    """A team ``crew``: a coordinator ``base``, agents ``cam0`` (0) and ``cam1`` (1), robots
    ``r0`` .. ``r2``, and ``late`` (agent 5), whose certificate expired yesterday."""
    root = tmp_path_factory.mktemp("teams") / "crew"
    teams.init_team(root)
    teams.add_member(root, "base", "coordinator")
    teams.add_member(root, "cam0", "agent")
    teams.add_member(root, "cam1", "agent")
    for robot in range(3):
        teams.add_member(root, f"r{robot}", "robot", robot)
    now = datetime.datetime.now(datetime.timezone.utc)
    teams.add_member(
        root,
        "late",
        "agent",
        5,
        not_before=now - datetime.timedelta(days=10),
        not_after=now - datetime.timedelta(days=1),
    )
    return root


@pytest.fixture(scope="module")
def strangers(tmp_path_factory) -> Path:
    """Another team, with an agent 0 of its own."""
    root = tmp_path_factory.mktemp("teams") / "strangers"
    teams.init_team(root)
    teams.add_member(root, "cam0", "agent", 0)
    return root


# ------------------------------------------------------------ folders


def test_a_member_folder_holds_what_one_machine_needs_readable_by_its_owner_only(crew):
    assert sorted(p.name for p in (crew / "cam1").iterdir()) == sorted(teams.MEMBER_FILES)
    assert not any((crew / name / teams.CA_KEY).exists() for name in ("base", "cam0", "r2"))
    for path in [crew / teams.CA_KEY, *(crew / "cam1").iterdir()]:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    members = {name: teams.load_member(crew / name) for name in ("base", "cam0", "cam1", "r2")}
    assert [(m.role, m.member_id, m.name) for m in members.values()] == [
        ("coordinator", None, "coordinator"),
        ("agent", 0, "agent-0"),
        ("agent", 1, "agent-1"),
        ("robot", 2, "robot-2"),
    ]
    roster = teams.roster(crew)
    assert roster["team"] == "crew" and roster["members"]["cam0"]["cn"] == "agent-0"


def test_bad_team_requests_are_clear_errors(crew, tmp_path):
    with pytest.raises(InputError, match="agent-1 is member 'cam1'"):
        teams.add_member(crew, "again", "agent", 1)
    with pytest.raises(InputError, match="choose one of"):
        teams.add_member(crew, "x", "pilot")
    with pytest.raises(InputError, match="not an empty folder"):
        teams.init_team(crew)
    with pytest.raises(InputError, match="the team's folder"):
        teams.load_member(crew)
    with pytest.raises(InputError, match="expired on"):
        teams.load_member(crew / "late")
    with pytest.raises(InputError, match="this command runs agent-1"):
        teams.check_role(teams.load_member(crew / "cam0"), "agent", 1)
    with pytest.raises(InputError, match="only TLS"):
        access.team_endpoints(["udp/127.0.0.1:7447"])
    assert access.team_endpoints(["tcp/10.0.0.1:7447", "tls/h:1"]) == (
        "tls/10.0.0.1:7447",
        "tls/h:1",
    )


def test_revoking_a_member_updates_the_team_and_its_member_folders(tmp_path):
    root = tmp_path / "t"
    teams.init_team(root)
    teams.add_member(root, "base", "coordinator")
    teams.add_member(root, "cam0", "agent")
    updated = teams.revoke_member(root, "cam0")
    assert updated == [root / "base", root / "cam0"]
    assert teams.load_member(root / "base").revoked == {"agent-0"}
    with pytest.raises(InputError, match="revoked"):
        teams.load_member(root / "cam0")
    rules = access.access_control(teams.load_member(root / "base"), peers=2)
    assert [s["cert_common_names"] for s in rules["subjects"]] == [["agent-1"]]


def test_the_command_line_makes_a_team(tmp_path):
    runner, root = CliRunner(), tmp_path / "t"
    for args in (
        ["init", str(root)],
        ["add", str(root), "base", "--role", "coordinator"],
        ["add", str(root), "cam", "--role", "agent", "--id", "4"],
        ["revoke", str(root), "cam"],
        ["list", str(root)],
    ):
        result = runner.invoke(app, ["team", *args])
        assert result.exit_code == 0, result.output
    assert "agent-4" in result.output and "yes" in result.output
    result = runner.invoke(
        app, ["team", "add", str(root), "x", "--role", "coordinator", "--id", "1"]
    )
    assert result.exit_code == 2 and "a coordinator has no --id" in result.output


# ------------------------------------------------------------ loopback TLS


class _Hub:
    """A team coordinator in this process: a hub for agents 0 and 1 on a TLS endpoint, its
    events collected by a thread of its own, as the runtime does."""

    def __init__(self, crew: Path, folder: Path | None = None) -> None:
        port, self.name = free_port(), f"t{uuid.uuid4().hex[:8]}"
        self.endpoint = f"tls/127.0.0.1:{port}"
        member = teams.load_member(folder or crew / "base")
        self.session = open_session(
            access.network_options(member, [self.endpoint], [], False, None, self.name, peers=2)
        )
        self.hub = ZenohHub(
            self.session, Keys(self.name), 2, codec.DEFAULT_MAX_BYTES, 2.0, certified=True
        )
        tasks = [
            AgentTask(
                agent=a, input_path="", config=config_to_dict(Config()), prior={"name": "simulated"}
            )
            for a in (0, 1)
        ]
        self.hub.start(tasks, lambda agent: "no rejoining in this test")
        self.events: list = []
        self.running = True
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while self.running:
            self.events.extend(self.hub.events(0.05))
            self.hub.acknowledge({})

    def wait_for(self, condition, what: str) -> None:
        deadline = time.monotonic() + WAIT_S
        while not any(condition(e) for e in list(self.events)):
            assert time.monotonic() < deadline, f"{what}: {self.events}"
            time.sleep(0.02)

    def join(self, folder: Path, check_validity: bool = True):
        """A session of the member in ``folder`` connected to this hub."""
        member = teams.load_member(folder, check_validity)
        return member, open_session(
            access.network_options(member, [], [self.endpoint], False, None, self.name)
        )

    def close(self) -> None:
        self.running = False
        self.thread.join(5)
        self.hub.stop([], interrupted=False)
        self.hub.close()
        self.session.close()


def _started(agent: int) -> bytes:
    return codec.encode(AgentStarted(agent=agent, pid=1, frames=4))


def _seq(seq: int = 0) -> bytes:
    return struct.pack("<QQ", 12345, seq)


def _quiet(hub: _Hub) -> list:
    """The hub's events after :data:`QUIET_S` of watching (what the test's puts changed)."""
    time.sleep(QUIET_S)
    return list(hub.events)


@pytest.mark.slow
def test_members_are_admitted_and_a_member_writing_under_another_id_changes_nothing(crew, caplog):
    hub = _Hub(crew)
    sessions = []
    try:
        with caplog.at_level(logging.INFO, logger="como3r.transport.team_access"):
            member, session = hub.join(crew / "cam0")
            sessions.append(session)
            link = ZenohAgentLink(session, Keys(hub.name, member.name), 0)
            assert link.fetch_task().agent == 0
            link.send(AgentStarted(agent=0, pid=1, frames=4))
            hub.wait_for(lambda e: isinstance(e, Received) and e.agent == 0, "agent 0's message")
        assert "coordinator: agent-0 connected" in caplog.text
        # agent 0's certificate, agent 1's id: its key ends in agent-0 (access control
        # allows no other), the hub drops it and says so
        session.put(Keys(hub.name, "agent-0").up(1, "AgentStarted"), _started(1), attachment=_seq())
        hub.wait_for(
            lambda e: isinstance(e, Rejected) and e.agent == 1,
            "the message under agent 1's id rejected",
        )
        [rejected] = [e for e in hub.events if isinstance(e, Rejected)]
        assert rejected.error == "sent under agent 1's id by the holder of certificate agent-0"
        # claiming agent 1's certificate name in the key: access control drops it
        session.put(Keys(hub.name, "agent-1").up(1, "AgentStarted"), _started(1), attachment=_seq())
        session.put(Keys(hub.name).up(1, "AgentStarted"), _started(1), attachment=_seq())
        # nor may it ask for agent 1's task (that would take over agent 1's id)
        replies = list(
            session.get(Keys(hub.name).task(1), timeout=QUIET_S, attachment=struct.pack("<Q", 7))
        )
        assert all(reply.ok is None for reply in replies)
        events = _quiet(hub)
        assert [e for e in events if e.agent == 1] == [rejected]
        link.close()
    finally:
        for session in sessions:
            session.close()
        hub.close()


@pytest.mark.slow
def test_peers_without_a_valid_certificate_change_nothing(crew, strangers, tmp_path, caplog, capfd):
    revoking = tmp_path / "base"  # the coordinator's folder with agent 1 revoked
    revoking.mkdir()
    for file in teams.MEMBER_FILES:
        (revoking / file).write_bytes((crew / "base" / file).read_bytes())
    (revoking / teams.REVOKED).write_text("agent-1\n")
    hub = _Hub(crew, revoking)
    sessions = []
    try:
        plain = open_session(
            ZenohOptions(connect=(hub.endpoint.replace("tls/", "tcp/"),), session=hub.name)
        )
        sessions.append(plain)
        # TLS that trusts the team's authority but shows no certificate of its own
        anonymous = {
            "transport/link/protocols": ["tls"],
            "listen/endpoints": [],
            "transport/link/tls": {
                "root_ca_certificate": str(crew / teams.CA_CERT),
                "verify_name_on_connect": False,
            },
        }
        sessions.append(
            open_session(
                ZenohOptions(
                    connect=(hub.endpoint,),
                    session=hub.name,
                    settings=tuple((k, json.dumps(v)) for k, v in anonymous.items()),
                )
            )
        )
        with caplog.at_level(logging.WARNING, logger="como3r.transport.team_access"):
            for folder, check in [
                (strangers / "cam0", True),
                (crew / "late", False),
                (crew / "cam1", True),
            ]:
                sessions.append(hub.join(folder, check)[1])
            time.sleep(QUIET_S)
        assert "coordinator: refusing every message of agent-1" in caplog.text
        assert "its certificate is revoked" in caplog.text
        for session in sessions:
            for agent in (0, 1):
                for sender in (None, f"agent-{agent}"):
                    session.put(
                        Keys(hub.name, sender).up(agent, "AgentStarted"),
                        _started(agent),
                        attachment=_seq(),
                    )
        assert _quiet(hub) == []
        # the TLS handshake refused all but the revoked member, whom access control refuses
        connected = {link.auth_identifier for link in hub.session.info.links()}
        assert connected == {"agent-1"}
        logged = capfd.readouterr().out  # Zenoh's own log (its TLS layer's warnings)
        for refusal in (
            "received corrupt message",
            "peer sent no certificates",
            "UnknownCA",
            "certificate expired",
        ):
            assert refusal in logged, refusal
    finally:
        for session in sessions:
            session.close()
        hub.close()


def _each(links: list[ZenohRobotLink], call) -> list:
    """``call(link)`` for every link, concurrently; what each returned."""
    results: list = [None] * len(links)

    def run(k: int) -> None:
        results[k] = call(links[k])

    threads = [threading.Thread(target=run, args=(k,), daemon=True) for k in range(len(links))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(WAIT_S)
    return results


@pytest.mark.slow
def test_a_robot_writing_under_another_robots_id_changes_nothing_and_is_logged(crew, caplog):
    port, name = free_port(), f"t{uuid.uuid4().hex[:8]}"
    endpoint = f"tls/127.0.0.1:{port}"
    members = [teams.load_member(crew / f"r{robot}") for robot in range(3)]
    # robots 1 and 2 give only robot 0's endpoint: they meet each other through gossip, on
    # a TLS port of the system's choosing, as they do without a team
    sessions = [
        open_session(
            access.network_options(
                member,
                [endpoint] if member.member_id == 0 else [],
                [] if member.member_id == 0 else [endpoint],
                False,
                None,
                name,
                peers=3,
            )
        )
        for member in members
    ]
    schedule = Schedule()
    links = [
        ZenohRobotLink(
            sessions[r],
            RobotKeys(name, members[r].name),
            r,
            3,
            RobotHello(robot=r, end_s=2.0, plan="p"),
            schedule.hears,
            2**16,
            certified=True,
        )
        for r in range(3)
    ]
    try:
        hellos = _each(links, lambda link: link.meet_team(wait_log_s=5.0))
        assert [sorted(h) for h in hellos] == [[0, 1, 2]] * 3
        with caplog.at_level(logging.WARNING):
            # robot 2 (valid, but not robot 1) sends robot 0 a message as robot 1: first with
            # its own name at the end of the key (dropped and logged by robot 0), then with
            # robot 1's (dropped by robot 0's access control)
            forged = codec.encode(
                EncodingRequest(sender=1, recipient=0, round=0, time_s=0.5, keyframes=[3])
            )
            for sender in ("robot-2", "robot-1"):
                sessions[2].put(
                    RobotKeys(name, sender).messages(0, 1),
                    forged,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
            genuine = EncodingRequest(sender=1, recipient=0, round=0, time_s=0.5, keyframes=[4])
            links[1].send(genuine)
            assert links[0].receive(WAIT_S) == genuine
            assert links[0].receive(QUIET_S) is None
        assert links[0].traffic.invalid == 1
        assert (
            "robot 0: dropped a message under robot '1''s key: sent by the holder of "
            "certificate robot-2" in caplog.text
        )
        between = EncodingRequest(sender=2, recipient=1, round=0, time_s=0.5, keyframes=[5])
        links[2].send(between)  # robots 1 and 2 talk directly
        assert links[1].receive(WAIT_S) == between
        _each(links, lambda link: link.finish([0, 1, 2], timeout=WAIT_S))
        assert "leaving before" not in caplog.text  # each saw the others' done tokens
    finally:
        for session in sessions:
            session.close()


# ------------------------------------------------------------ the commands


def test_without_team_a_networked_command_warns_once_that_the_network_is_open(crew, tmp_path):
    missing = str(tmp_path / "nothing")
    common = ["agent", missing, "--id", "0", "--connect", "tcp/127.0.0.1:9", "--prior", "simulated"]
    result = CliRunner().invoke(app, common)
    assert result.exit_code == 2 and "agent input does not exist" in result.output
    assert result.output.count("warning: open network") == 1
    assert OPEN_NETWORK.split(":")[0] == "warning"
    result = CliRunner().invoke(app, [*common, "--team", str(crew / "cam0")])
    assert result.exit_code == 2 and "agent input does not exist" in result.output
    assert "open network" not in result.output
    result = CliRunner().invoke(app, [*common, "--team", str(crew / "cam1")])
    assert result.exit_code == 2 and "this command runs agent-0" in result.output


@pytest.mark.slow
def test_a_team_run_merges_as_before_and_logs_what_it_refused(
    tiny_scene, crew, team, tmp_path
) -> None:
    scene = tiny_scene(frames=12, seed=0, overlap=0.5)
    endpoint = team.endpoint.replace("tcp/", "tls/")
    out = tmp_path / "net"
    team.start(
        "coordinator",
        "coordinator",
        "--listen",
        endpoint,
        "--out",
        str(out),
        "--agents",
        "2",
        "--prior",
        "simulated",
        *SIZE,
        "--team",
        str(crew / "base"),
    )
    # a stranger on plain TCP, and a holder of agent 0's certificate writing as agent 1
    plain = open_session(ZenohOptions(connect=(team.endpoint,), session=team.session))
    member, forger = teams.load_member(crew / "cam0"), None
    try:
        forger = open_session(
            access.network_options(member, [], [endpoint], False, None, team.session)
        )
        deadline = time.monotonic() + 240
        while not any(
            r.ok is not None
            for r in forger.liveliness().get(Keys(team.session).coordinator(), timeout=1.0)
        ):
            assert time.monotonic() < deadline, team.log("coordinator")
        forger.put(
            Keys(team.session, member.name).up(1, "AgentStarted"),
            _started(1),
            attachment=_seq(),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        plain.put(Keys(team.session).up(1, "AgentStarted"), _started(1), attachment=_seq())
        for agent, name in ((0, "cam0"), (1, "cam1")):
            team.start(
                f"agent{agent}",
                "agent",
                "--connect",
                endpoint,
                "--id",
                str(agent),
                str(scene / f"agent_{agent}"),
                "--prior",
                "simulated",
                "--team",
                str(crew / name),
            )
        for name in ("coordinator", "agent0", "agent1"):
            team.wait(name)
    finally:
        for session in (plain, forger):
            if session is not None:
                session.close()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["components"] == [[0, 1]]
    assert [a["status"] for a in metrics["runtime"]["agents"]] == ["finished", "finished"]
    log = team.log("coordinator")
    assert "open network" not in log
    assert (
        "dropped a message from agent 1: sent under agent 1's id by the holder of "
        "certificate agent-0"
    ) in log
    assert "zenoh_link_tls" in log  # the plain TCP peer's refused handshake

"""What a team member's process makes of its member folder (:mod:`como3r.transport.team`):
its Zenoh configuration (``--team``; manual: docs/networked.md, "Across machines").

- Transport: mutual TLS only (``transport/link/protocols`` is ``tls``): a peer must show a
  certificate of the team's authority, valid now; a plain TCP peer, a peer without a
  certificate, with one of another authority or an expired one fails the handshake (Zenoh
  logs it) and never exchanges a message. Host names are not checked: the certificate, not
  the address, is the identity.
- Access control (Zenoh's ``access_control``, default deny), from the peer's certificate:
  agent K may write its own messages, its liveliness and its task query only; only the
  coordinator writes what goes to agents (pose updates, acknowledgements, tasks); robot K
  writes only messages from robot K. Every message key ends in its sender's certificate
  name (``.../up/<Type>/agent-3``, ``.../from/3/robot-3``), which access control pins: the
  application compares it with the id the key and the message claim, and drops and logs a
  message sent under another member's id (Zenoh's own refusals are silent at its default
  log levels).
- Revocation: a certificate name in the process's ``revoked.txt`` gets no rights (every
  message from it is refused) and its connection is logged (:class:`LinkWatch`). Zenoh
  cannot check revocation lists, so revocation is by certificate name, i.e. by role and
  id: a revoked id stays revoked in the team (a replacement member takes a new id).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from como3r.errors import InputError
from como3r.transport.team import CA_CERT, CERT, KEY, Member, common_name

logger = logging.getLogger(__name__)

#: every kind of message Zenoh's access control filters
MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)


def team_endpoints(endpoints: Iterable[str]) -> tuple[str, ...]:
    """``endpoints`` as a team speaks them: ``tcp/`` ones are taken as ``tls/``.

    Raises:
        InputError: an endpoint of another protocol (udp, ws, ...).
    """
    out = []
    for endpoint in endpoints:
        protocol, _, address = endpoint.partition("/")
        if protocol not in ("tcp", "tls") or not address:
            raise InputError(f"endpoint {endpoint!r}: a team speaks only TLS (tls/HOST:PORT)")
        out.append(f"tls/{address}")
    return tuple(out)


def zenoh_settings(member: Member, peers: int | None = None) -> dict[str, Any]:
    """The Zenoh configuration of ``member``'s process, as ``{config path: value}``:
    mutual TLS with its key and certificate and access control from its peers'
    certificates (module docstring).

    Args:
        peers: agents of the coordinator's run, or robots of a robot's team (ids 0 to
            peers-1); unused for an agent (its one peer is the coordinator).
    """
    tls = {
        "root_ca_certificate": member.path(CA_CERT),
        "listen_private_key": member.path(KEY),
        "listen_certificate": member.path(CERT),
        "connect_private_key": member.path(KEY),
        "connect_certificate": member.path(CERT),
        "enable_mtls": True,
        "verify_name_on_connect": False,
        "close_link_on_expiration": True,
    }
    return {
        "transport/link/protocols": ["tls"],
        "transport/link/tls": tls,
        "access_control": access_control(member, peers),
    }


def access_control(member: Member, peers: int | None = None) -> dict[str, Any]:
    """Zenoh's ``access_control`` of ``member``'s process: default deny; every peer it may
    meet gets the rights of its certificate (module docstring); revoked ones get none."""
    grants: dict[str, list[tuple[list[str], list[str]]]] = {}  # peer cn -> (messages, keys)
    if member.role == "coordinator":
        for agent in range(peers or 0):
            grants[common_name("agent", agent)] = agent_rights(agent)
    elif member.role == "agent":
        grants["coordinator"] = coordinator_rights(member.member_id)
    else:
        for robot in range(peers or 0):
            if robot != member.member_id:
                grants[common_name("robot", robot)] = robot_rights(robot, member.member_id)
    rules, subjects, policies = [], [], []
    for cn, rights in grants.items():
        if cn in member.revoked:
            continue
        subjects.append({"id": cn, "cert_common_names": [cn]})
        ids = []
        for index, (messages, keys) in enumerate(rights):
            ids.append(f"{cn}/{index}")
            rules.append(
                {
                    "id": ids[-1],
                    "permission": "allow",
                    "flows": ["ingress"],
                    "messages": messages,
                    "key_exprs": keys,
                }
            )
        ids.append(f"{cn}/out")  # what this process sends it: its subscriptions filter that
        rules.append(
            {
                "id": ids[-1],
                "permission": "allow",
                "flows": ["egress"],
                "messages": list(MESSAGES),
                "key_exprs": ["**"],
            }
        )
        policies.append({"id": f"{cn}/policy", "rules": ids, "subjects": [cn]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def agent_rights(agent: int) -> list[tuple[list[str], list[str]]]:
    """What the coordinator takes from agent ``agent``'s certificate."""
    own = f"como3r/*/agent/{agent}"
    return [
        (["put"], [f"como3r/*/agent/*/up/*/{common_name('agent', agent)}"]),
        (["liveliness_token"], [f"{own}/alive/*"]),
        (["query"], [f"{own}/task"]),
        (["declare_subscriber"], [f"{own}/**"]),
        (["declare_liveliness_subscriber", "liveliness_query"], ["como3r/*/coordinator"]),
    ]


def coordinator_rights(agent: int | None) -> list[tuple[list[str], list[str]]]:
    """What agent ``agent`` takes from the coordinator's certificate."""
    own = f"como3r/*/agent/{agent}"
    return [
        (["put"], [f"{own}/down/*", f"{own}/ack"]),
        (["liveliness_token"], ["como3r/*/coordinator"]),
        (["declare_queryable"], ["como3r/*/agent/*/task"]),
        (["reply"], [f"{own}/task"]),
        (["declare_subscriber"], ["como3r/*/agent/*/up/**"]),
        (["declare_liveliness_subscriber", "liveliness_query"], ["como3r/*/agent/*/alive/*"]),
    ]


def robot_rights(peer: int, robot: int | None) -> list[tuple[list[str], list[str]]]:
    """What robot ``robot`` takes from robot ``peer``'s certificate."""
    theirs = f"como3r/*/robot/{peer}"
    return [
        (["put"], [f"como3r/*/robot/{robot}/from/*/{common_name('robot', peer)}"]),
        (["liveliness_token"], [f"{theirs}/alive", f"{theirs}/done"]),
        (["declare_queryable"], [f"{theirs}/hello"]),
        (["query", "reply"], ["como3r/*/robot/*/hello"]),
        (["declare_subscriber"], [f"{theirs}/from/**"]),
        (
            ["declare_liveliness_subscriber", "liveliness_query"],
            ["como3r/*/robot/*/alive", "como3r/*/robot/*/done"],
        ),
    ]


class LinkWatch:
    """Logs each peer that connects to a team member's session, by its certificate name,
    and warns of a revoked one (it has no rights here, as a peer not of this run).
    Called with the session once it is open (``ZenohOptions.on_open``).

    Args:
        member: the member.
        admitted: certificate names with rights here (the access control's subjects).
    """

    def __init__(self, member: Member, admitted: Iterable[str]) -> None:
        self.member, self.admitted = member, frozenset(admitted)
        self.listeners: list[Any] = []

    def __call__(self, session: Any) -> None:
        self.listeners.append(
            session.info.declare_link_events_listener(self._on_link, history=True)
        )

    def _on_link(self, event: Any) -> None:
        import zenoh

        if event.kind != zenoh.SampleKind.PUT:
            return
        name = event.link.auth_identifier or "(none)"
        if name in self.member.revoked:
            logger.warning(
                "%s: refusing every message of %s (%s): its certificate is revoked",
                self.member.name,
                name,
                event.link.dst,
            )
        elif name not in self.admitted:  # e.g. another agent, found by gossip: no threat
            logger.info(
                "%s: refusing every message of %s (%s): not a peer of this run",
                self.member.name,
                name,
                event.link.dst,
            )
        else:
            logger.info("%s: %s connected (%s)", self.member.name, name, event.link.dst)


def network_options(
    member: Member,
    listen: Iterable[str],
    connect: Iterable[str],
    scouting: bool,
    config_file: Path | None,
    session: str,
    peers: int | None = None,
) -> Any:
    """The :class:`~como3r.transport.zenoh_protocol.ZenohOptions` of ``member``'s process:
    its endpoints as TLS ones (:func:`team_endpoints`), :func:`zenoh_settings` and a
    :class:`LinkWatch`; ``peers`` as for :func:`zenoh_settings`."""
    from como3r.transport.zenoh_protocol import ZenohOptions

    listen, connect = team_endpoints(listen), team_endpoints(connect)
    settings = zenoh_settings(member, peers)
    if not listen:  # Zenoh's default is a plain TCP port, which a team does not speak
        # robots: a TLS port of the system's choosing, which gossip tells their peers of so
        # that they connect directly, as without a team; an agent needs only its coordinator
        settings["listen/endpoints"] = ["tls/[::]:0"] if member.role == "robot" else []
    return ZenohOptions(
        listen,
        connect,
        scouting,
        config_file,
        session,
        tuple((path, json.dumps(value)) for path, value in settings.items()),
        member.name,
        LinkWatch(member, admitted(settings)),
    )


def admitted(settings: dict[str, Any]) -> list[str]:
    """The certificate names with rights in ``settings`` (:func:`zenoh_settings`)."""
    return [
        name
        for subject in settings["access_control"]["subjects"]
        for name in subject["cert_common_names"]
    ]

"""A team that admits only the team: a certificate authority and its members (``como3r team``;
manual: docs/networked.md, "Across machines").

A team is a folder made by :func:`init_team`: the authority's key (``ca.key``, it never
leaves this folder) and certificate (``ca.pem``), the roster (``team.json``) and the
revocation list (``revoked.txt``). :func:`add_member` writes a member folder
``TEAM/NAME/``: the member's key (``key.pem``), its certificate (``cert.pem``), the
authority's certificate and a copy of the revocation list; it is all one machine needs.
Every file is readable by its owner only (0600).

A member's certificate names its role and id in its common name: ``coordinator``,
``agent-<K>`` or ``robot-<K>``. Keys are ECDSA P-256, which Zenoh's TLS (rustls) accepts
on both ends of a link.

What a member's process makes of it (mutual TLS, access control from the peers'
certificates, revocation) is :mod:`como3r.transport.team_access`.
"""

from __future__ import annotations

import datetime
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from como3r.errors import InputError

ROLES = ("coordinator", "agent", "robot")
CA_KEY, CA_CERT, ROSTER, REVOKED = "ca.key", "ca.pem", "team.json", "revoked.txt"
KEY, CERT = "key.pem", "cert.pem"
MEMBER_FILES = (KEY, CERT, CA_CERT, REVOKED)
#: how long a member's certificate is valid by default [days]
DEFAULT_VALID_DAYS = 365
CA_VALID_DAYS = 3650
#: clock skew between machines allowed at the start of a certificate
SKEW = datetime.timedelta(minutes=5)
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def common_name(role: str, member_id: int | None) -> str:
    """The certificate name of ``role`` with id ``member_id`` (None for the coordinator)."""
    return "coordinator" if role == "coordinator" else f"{role}-{member_id}"


def parse_common_name(name: str) -> tuple[str, int | None] | None:
    """``(role, id)`` of a certificate name, or None if it is not a member's."""
    if name == "coordinator":
        return "coordinator", None
    match = re.fullmatch(r"(agent|robot)-(\d+)", name)
    return (match.group(1), int(match.group(2))) if match else None


@dataclass(frozen=True)
class Member:
    """A member folder, read (:func:`load_member`).

    Attributes:
        folder: the member folder.
        role: ``coordinator``, ``agent`` or ``robot``.
        member_id: the agent's or robot's id (None for the coordinator).
        name: its certificate's common name (:func:`common_name`).
        not_after: the end of its certificate's validity (UTC).
        revoked: certificate names this member refuses.
    """

    folder: Path
    role: str
    member_id: int | None
    name: str
    not_after: datetime.datetime
    revoked: frozenset[str]

    def path(self, file: str) -> str:
        return str(self.folder / file)


# ------------------------------------------------------------ the authority


def init_team(folder: Path) -> None:
    """Make a team's certificate authority in ``folder`` (new or empty).

    Raises:
        InputError: ``folder`` exists and is not empty, or cannot be written.
    """
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec

    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise InputError(f"{folder}: exists and is not an empty folder (a team is made once)")
    name = folder.resolve().name
    if not _NAME.match(name):
        raise InputError(f"{folder}: use letters, digits, '.', '-' and '_' in a team's name")
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(x509.NameOID.COMMON_NAME, f"como3r-team-{name}")])
    now = _now()
    builder = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - SKEW)
        .not_valid_after(now + datetime.timedelta(days=CA_VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(sign_certificates=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
    )
    certificate = _sign(builder, key)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        os.chmod(folder, 0o700)
        _write(folder / CA_KEY, _key_pem(key))
        _write(folder / CA_CERT, _cert_pem(certificate))
        _write(folder / ROSTER, json.dumps({"team": name, "members": {}}, indent=1).encode())
        _write(folder / REVOKED, b"")
    except OSError as exc:
        raise InputError(f"{folder}: {exc.strerror}") from None


def add_member(
    team: Path,
    name: str,
    role: str,
    member_id: int | None = None,
    valid_days: float = DEFAULT_VALID_DAYS,
    not_before: datetime.datetime | None = None,
    not_after: datetime.datetime | None = None,
) -> Path:
    """Write the member folder ``team/name`` of a new member (module docstring).

    Args:
        team: the team folder (:func:`init_team`).
        name: the member's folder name (e.g. the machine's).
        role: ``coordinator``, ``agent`` or ``robot``.
        member_id: the agent's or robot's id (None: the smallest free one of that role);
            none for the coordinator.
        valid_days: how long its certificate is valid from now.
        not_before, not_after: the validity instead (UTC), for tests of expiry.

    Returns:
        The member folder.

    Raises:
        InputError: not a team folder, a bad name, role or id, or a role and id the team
            has already given out (revoked or not).
    """
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec

    roster = _roster(team)
    if role not in ROLES:
        raise InputError(f"--role {role!r}: choose one of {', '.join(ROLES)}")
    if not _NAME.match(name) or name in (CA_KEY, CA_CERT, ROSTER, REVOKED):
        raise InputError(f"member name {name!r}: use letters, digits, '.', '-' and '_'")
    if role == "coordinator" and member_id is not None:
        raise InputError("a coordinator has no --id")
    taken = {entry["cn"] for entry in roster["members"].values()}
    if member_id is None and role != "coordinator":
        member_id = next(k for k in range(len(taken) + 1) if common_name(role, k) not in taken)
    if member_id is not None and member_id < 0:
        raise InputError(f"--id {member_id}: ids start at 0")
    cn = common_name(role, member_id)
    if cn in taken:
        holder = next(n for n, e in roster["members"].items() if e["cn"] == cn)
        raise InputError(
            f"{cn} is member {holder!r} of team {roster['team']} already (a "
            f"revoked id is not given out again)"
        )
    folder = team / name
    if folder.exists():
        raise InputError(f"{folder}: exists already")
    if valid_days <= 0:
        raise InputError(f"--valid-days {valid_days}: give a positive number of days")
    ca_key, ca_cert = _authority(team)
    key = ec.generate_private_key(ec.SECP256R1())
    start = not_before if not_before is not None else _now() - SKEW
    end = not_after if not_after is not None else _now() + datetime.timedelta(days=valid_days)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(x509.NameOID.COMMON_NAME, cn)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(sign_certificates=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage(
                [x509.ExtendedKeyUsageOID.SERVER_AUTH, x509.ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        # rustls wants a subject alternative name; the name, not a host, is what counts
        .add_extension(x509.SubjectAlternativeName([x509.DNSName(cn)]), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
    )
    certificate = _sign(builder, ca_key)
    try:
        folder.mkdir()
        os.chmod(folder, 0o700)
        _write(folder / KEY, _key_pem(key))
        _write(folder / CERT, _cert_pem(certificate))
        _write(folder / CA_CERT, (team / CA_CERT).read_bytes())
        _write(folder / REVOKED, (team / REVOKED).read_bytes())
    except OSError as exc:
        raise InputError(f"{folder}: {exc.strerror}") from None
    roster["members"][name] = {
        "role": role,
        "id": member_id,
        "cn": cn,
        "serial": format(certificate.serial_number, "x"),
        "not_after": end.isoformat(),
    }
    _write(team / ROSTER, json.dumps(roster, indent=1).encode())
    return folder


def revoke_member(team: Path, name: str) -> list[Path]:
    """Revoke member ``name``: its certificate name goes into the team's ``revoked.txt``
    and into the copy of every member folder still under ``team``.

    Returns:
        The member folders updated (copy each to its machine, or its ``revoked.txt``).

    Raises:
        InputError: not a team folder, or no such member.
    """
    roster = _roster(team)
    if name not in roster["members"]:
        raise InputError(f"team {roster['team']} has no member {name!r}")
    cn = roster["members"][name]["cn"]
    names = _read_revoked(team / REVOKED)
    if cn not in names:
        text = (team / REVOKED).read_text() + f"{cn}\n"
        _write(team / REVOKED, text.encode())
    updated = []
    for member in sorted(roster["members"]):
        folder = team / member
        if (folder / REVOKED).is_file():
            _write(folder / REVOKED, (team / REVOKED).read_bytes())
            updated.append(folder)
    return updated


def roster(team: Path) -> dict[str, Any]:
    """The team's roster: ``{"team": name, "members": {name: {role, id, cn, serial,
    not_after}}}`` plus ``revoked``, the revoked certificate names."""
    data = _roster(team)
    data["revoked"] = sorted(_read_revoked(team / REVOKED))
    return data


# ------------------------------------------------------------ a member


def load_member(folder: Path, check_validity: bool = True) -> Member:
    """Read the member folder ``folder`` (``--team TEAM/NAME``).

    Args:
        check_validity: refuse a certificate that is expired, not yet valid, not issued
            by the folder's authority or revoked (False: read it as it is, for tests of
            what peers make of such a member).

    Raises:
        InputError: a missing or unreadable file, or (``check_validity``) a certificate
            this member's peers would refuse.
    """
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature

    if not folder.is_dir():
        raise InputError(f"--team {folder}: no such member folder (como3r team add)")
    if (folder / CA_KEY).exists():
        raise InputError(
            f"--team {folder}: this is the team's folder (with the authority's "
            f"key); give a member's folder, TEAM/NAME"
        )
    missing = [file for file in MEMBER_FILES if not (folder / file).is_file()]
    if missing:
        raise InputError(
            f"--team {folder}: missing {', '.join(missing)} (a member folder "
            f"is made by como3r team add)"
        )
    try:
        certificate = x509.load_pem_x509_certificate((folder / CERT).read_bytes())
        authority = x509.load_pem_x509_certificate((folder / CA_CERT).read_bytes())
    except (OSError, ValueError) as exc:
        raise InputError(f"--team {folder}: unreadable certificate ({exc})") from None
    names = certificate.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)
    cn = str(names[0].value) if names else ""
    parsed = parse_common_name(cn)
    if parsed is None:
        raise InputError(f"--team {folder}: {cn!r} is not a member's certificate")
    revoked = frozenset(_read_revoked(folder / REVOKED))
    member = Member(folder, parsed[0], parsed[1], cn, certificate.not_valid_after_utc, revoked)
    if check_validity:
        now = _now()
        if now > certificate.not_valid_after_utc:
            raise InputError(
                f"--team {folder}: its certificate expired on "
                f"{certificate.not_valid_after_utc:%Y-%m-%d %H:%M} UTC"
            )
        if now < certificate.not_valid_before_utc:
            raise InputError(
                f"--team {folder}: its certificate is valid from "
                f"{certificate.not_valid_before_utc:%Y-%m-%d %H:%M} UTC only"
            )
        try:
            certificate.verify_directly_issued_by(authority)
        except (InvalidSignature, ValueError, TypeError) as exc:
            raise InputError(
                f"--team {folder}: its certificate is not issued by the "
                f"folder's authority ({type(exc).__name__})"
            ) from None
        if cn in revoked:
            raise InputError(f"--team {folder}: its certificate ({cn}) is revoked")
    return member


def check_role(member: Member, role: str, member_id: int | None = None) -> None:
    """Refuse a member folder of another role or id than the command's.

    Raises:
        InputError: the certificate names another role or id.
    """
    if member.role != role or (member_id is not None and member.member_id != member_id):
        wanted = (
            f"a {role}"
            if role != "coordinator" and member_id is None
            else common_name(role, member_id)
        )
        raise InputError(
            f"--team {member.folder}: its certificate is {member.name}'s, this "
            f"command runs {wanted}"
        )


# ------------------------------------------------------------ files


def _roster(team: Path) -> dict[str, Any]:
    try:
        data = json.loads((team / ROSTER).read_text())
    except (OSError, ValueError):
        raise InputError(f"{team}: not a team folder (como3r team init)") from None
    if not (team / CA_KEY).is_file():
        raise InputError(f"{team}: the authority's key ({CA_KEY}) is missing")
    return data


def _authority(team: Path) -> tuple[Any, Any]:
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    try:
        key = serialization.load_pem_private_key((team / CA_KEY).read_bytes(), password=None)
        certificate = x509.load_pem_x509_certificate((team / CA_CERT).read_bytes())
    except (OSError, ValueError) as exc:
        raise InputError(f"{team}: unreadable authority ({exc})") from None
    return key, certificate


def _read_revoked(path: Path) -> set[str]:
    """Certificate names, one a line (``#`` starts a comment)."""
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror}") from None
    return {line.split("#", 1)[0].strip() for line in lines} - {""}


def _write(path: Path, data: bytes) -> None:
    """Write ``path`` readable by its owner only (made so, never widened on the way)."""
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "wb") as file:
        file.write(data)
    os.chmod(path, 0o600)


def _now() -> datetime.datetime:
    return datetime.datetime.now(datetime.timezone.utc)


def _key_usage(sign_certificates: bool) -> Any:
    from cryptography import x509

    return x509.KeyUsage(
        digital_signature=not sign_certificates,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=sign_certificates,
        crl_sign=sign_certificates,
        encipher_only=False,
        decipher_only=False,
    )


def _sign(builder: Any, key: Any) -> Any:
    from cryptography.hazmat.primitives import hashes

    return builder.sign(key, hashes.SHA256())


def _key_pem(key: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _cert_pem(certificate: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return certificate.public_bytes(serialization.Encoding.PEM)

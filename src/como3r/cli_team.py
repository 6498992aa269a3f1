"""``como3r team``: a team's certificate authority and its members' folders
(:mod:`como3r.transport.team`; manual: docs/commands/team.md)."""

from __future__ import annotations

from pathlib import Path

import typer

from como3r.cli_common import Command, OneLineErrorsGroup, console, print_rows, user_errors

team_app = typer.Typer(
    cls=OneLineErrorsGroup,
    no_args_is_help=True,
    help="A team that admits only the team: its certificate authority and "
    "members (--team of coordinator, agent, robot).",
)

TeamArgument = typer.Argument(
    ...,
    metavar="TEAM",
    show_default=False,
    help="The team's folder (it holds the authority's key: keep it off the robots).",
)


@team_app.command("init", cls=Command)
@user_errors
def init(team: Path = TeamArgument) -> None:
    """Make a team: a certificate authority in the new folder TEAM."""
    from como3r.transport.team import init_team

    init_team(team)
    console.print(
        f"team {team.resolve().name}: authority in {team} (its key, ca.key, stays "
        f"there); add members with como3r team add {team} NAME --role ...",
        highlight=False,
        soft_wrap=True,
    )


@team_app.command("add", cls=Command)
@user_errors
def add(
    team: Path = TeamArgument,
    name: str = typer.Argument(
        ...,
        metavar="NAME",
        show_default=False,
        help="The member's folder name, e.g. its machine's.",
    ),
    role: str = typer.Option(..., "--role", help="coordinator | agent | robot"),
    member_id: int | None = typer.Option(
        None,
        "--id",
        min=0,
        help="The agent's or robot's id (default: the smallest free "
        "one); none for the coordinator.",
    ),
    valid_days: float = typer.Option(
        365.0, "--valid-days", min=0.001, help="How long its certificate is valid."
    ),
) -> None:
    """Write the member folder TEAM/NAME, all one machine needs.

    Its key, its certificate (role and id), the authority's certificate and the revocation
    list, readable by their owner only; copy the folder to the member's machine."""
    from como3r.transport.team import add_member, load_member

    folder = add_member(team, name, role, member_id, valid_days)
    member = load_member(folder)
    console.print(
        f"{folder}: {member.name}, valid until {member.not_after:%Y-%m-%d} UTC; "
        f"copy the folder to its machine and pass --team {folder}",
        highlight=False,
        soft_wrap=True,
    )


@team_app.command("revoke", cls=Command)
@user_errors
def revoke(
    team: Path = TeamArgument,
    name: str = typer.Argument(
        ..., metavar="NAME", show_default=False, help="The member to revoke."
    ),
) -> None:
    """Revoke member NAME: its role and id get no rights in the team any more.

    The member folders under TEAM get the new revoked.txt; copy it to their machines."""
    from como3r.transport.team import revoke_member

    updated = revoke_member(team, name)
    console.print(
        f"revoked {name}; updated revoked.txt in {len(updated)} member folder(s) "
        f"under {team}: copy it to their machines",
        highlight=False,
        soft_wrap=True,
    )


@team_app.command("list", cls=Command)
@user_errors
def list_members(team: Path = TeamArgument) -> None:
    """The team's members: role, id, certificate name, validity, revoked or not."""
    from como3r.transport.team import roster

    data = roster(team)
    rows = [
        {
            "member": name,
            "certificate": entry["cn"],
            "valid until": entry["not_after"][:10],
            "revoked": "yes" if entry["cn"] in data["revoked"] else "",
        }
        for name, entry in sorted(data["members"].items())
    ]
    if rows:
        print_rows(f"team {data['team']}", rows)
    else:
        console.print(f"team {data['team']}: no members yet", highlight=False)

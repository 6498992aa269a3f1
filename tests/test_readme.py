"""The README's command synopsis is the CLI: every command and option, no more, no fewer, and
the choices it lists are the ones the code accepts (issue 17: "a README that stays true")."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import typer

from como3r.cli import app
from como3r.data.readers import FORMATS
from como3r.data.synth import PRESETS
from como3r.decentralized.odometry_sim import ODOMETRY_PRESETS
from como3r.prior.mast3r.precision import PRECISIONS
from como3r.runtime.pipeline import PRIORS
from como3r.viewer import MODES as VIEWER_MODES

README = Path(__file__).resolve().parents[1] / "README.md"
GROUP = "como3r"


def _synopsis() -> str:
    """The code block right after the README's "## Commands" heading."""
    text = README.read_text()
    block = re.search(r"^## Commands\n\n```\n(.*?)^```", text, re.S | re.M)
    assert block is not None, "README.md has no code block after '## Commands'"
    return block.group(1)


def _readme_commands() -> dict[str, str]:
    """Command path (``run``, ``weights fetch``, ``como3r`` for the group) -> its synopsis
    text, continuation lines included."""
    commands: dict[str, str] = {}
    current = None
    for line in _synopsis().splitlines():
        if line.startswith("como3r"):
            words = line.split()[1:]
            name = []
            for word in words:
                if not re.fullmatch(r"[a-z]+", word):
                    break
                name.append(word)
            current = " ".join(name) or GROUP
            commands[current] = line
        elif line.strip() and current is not None:
            commands[current] += " " + line.strip()
    return commands


def _options(synopsis: str) -> set[str]:
    return set(re.findall(r"(?<![\w-])(--?[a-z][a-z0-9-]*)", synopsis))


def _cli_commands() -> dict[str, set[str]]:
    """Command path -> the option names click knows for it (``--help`` aside)."""
    root = typer.main.get_command(app)
    found = {GROUP: {name for p in root.params for name in p.opts}}

    def walk(group, prefix: list[str]) -> None:
        for name, command in group.commands.items():
            if hasattr(command, "commands"):
                walk(command, [*prefix, name])
            else:
                found[" ".join([*prefix, name])] = {
                    opt
                    for p in command.params
                    if p.param_type_name == "option"
                    for opt in (*p.opts, *p.secondary_opts)
                }  # not arguments (export's RUN)

    walk(root, [])
    return found


def test_every_command_is_in_the_synopsis_and_no_other() -> None:
    assert sorted(_readme_commands()) == sorted(_cli_commands())


@pytest.mark.parametrize("command", sorted(_cli_commands()))
def test_the_synopsis_lists_exactly_the_options_of(command: str) -> None:
    documented = _options(_readme_commands().get(command, ""))
    assert documented == _cli_commands()[command], (
        f"README synopsis of {command!r}: missing {sorted(_cli_commands()[command] - documented)}"
        f", not in the CLI {sorted(documented - _cli_commands()[command])}"
    )


@pytest.mark.parametrize(
    "option, accepted",
    [
        ("--prior", set(PRIORS)),
        ("--precision", set(PRECISIONS)),
        ("--odometry", {*ODOMETRY_PRESETS, "none"}),
        ("--mode", {"centralized", "decentralized"}),
        ("--device", {"cpu", "cuda"}),
        ("--format", set(FORMATS)),
        ("--viewer", set(VIEWER_MODES)),
    ],
)
def test_listed_choices_are_the_accepted_ones(option: str, accepted: set[str]) -> None:
    listed = re.search(rf"{option} ([a-z0-9]+(?:\|[a-z0-9]+)+)", _synopsis())
    assert listed is not None, f"{option} lists no choices in the README synopsis"
    assert set(listed.group(1).split("|")) == accepted


def test_the_preset_list_names_every_preset() -> None:
    paragraph = re.search(r"^Synthetic presets: (.*?)\n\n", README.read_text(), re.S | re.M)
    assert paragraph is not None
    assert set(re.findall(r"`([a-z-]+)`", paragraph.group(1))) == set(PRESETS)

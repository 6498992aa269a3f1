"""Every command's ``--help`` says what its source says: no ``[...]`` taken for rich markup
and dropped (``pip install "como3r[viewer]"`` once read ``pip install "como3r"``), and
positional arguments named as a user types them (``A B``, not typer's ``{A} {B}``)."""

from __future__ import annotations

import re

import pytest
import typer
from typer.testing import CliRunner

from como3r.cli import app

runner = CliRunner()


def _commands() -> dict[tuple[str, ...], object]:
    """Command path (``()`` for ``como3r`` itself) -> its click command, groups included."""
    found: dict[tuple[str, ...], object] = {}

    def walk(command, path: tuple[str, ...]) -> None:
        found[path] = command
        for name, sub in getattr(command, "commands", {}).items():
            walk(sub, (*path, name))

    walk(typer.main.get_command(app), ())
    return found


COMMANDS = _commands()


def _texts(command) -> list[str]:
    """The help strings the source gives: the command's and each parameter's."""
    texts = [command.help or ""]
    texts += [getattr(p, "help", None) or "" for p in command.params]
    return texts


def _help(path: tuple[str, ...]) -> str:
    result = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "100"})
    assert result.exit_code == 0, result.output
    return result.output


def _squeezed(text: str) -> str:
    """``text`` without white space and the help boxes' borders (wrapping moves them)."""
    return re.sub(r"[\s│╭╮╰╯─]", "", text)


@pytest.mark.parametrize("path", sorted(COMMANDS), ids=lambda p: " ".join(p) or "como3r")
def test_help_shows_every_bracket_of_the_source(path: tuple[str, ...]) -> None:
    shown = _squeezed(_help(path))
    brackets = [b for text in _texts(COMMANDS[path]) for b in re.findall(r"\[[^\[\]]*\]", text)]
    lost = [b for b in brackets if _squeezed(b) not in shown]
    assert not lost, f"rich markup swallowed {lost}: escape them (rich.markup.escape)"
    assert "\\[" not in shown, "an escape shows in the help (escaped twice?)"


@pytest.mark.parametrize("path", sorted(COMMANDS), ids=lambda p: " ".join(p) or "como3r")
def test_help_names_arguments_without_braces(path: tuple[str, ...]) -> None:
    shown = _help(path)
    assert not re.search(r"\{[A-Z_]+\}", shown), shown


def test_the_viewer_help_names_the_extra_to_install() -> None:
    assert 'pip install "como3r[viewer]"' in _help(("run",)).replace("\n", " ")


def test_usage_lines_name_the_arguments() -> None:
    assert re.search(r"merge \[OPTIONS\] A B\s", _help(("merge",)))
    assert re.search(r"export \[OPTIONS\] RUN\s", _help(("export",)))
    assert re.search(r"team add \[OPTIONS\] TEAM NAME\s", _help(("team", "add")))

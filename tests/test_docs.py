"""The manual stays true: it builds with ``mkdocs build --strict`` (broken links and anchors
fail), every ``como3r`` command it or the README shows is one the CLI accepts, the synopsis
is the CLI (every command and option, no more, no fewer, issue 17: "a README that stays
true"), and the configuration reference is generated from the code (issue 40)."""

from __future__ import annotations

import importlib
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import typer

from como3r.cli import app
from como3r.config import Config, _flatten, apply_overrides, config_to_dict
from como3r.data.readers import FORMATS
from como3r.data.synth import PRESETS
from como3r.decentralized.odometry_sim import ODOMETRY_PRESETS
from como3r.errors import ConfigError
from como3r.prior.mast3r.precision import PRECISIONS
from como3r.runtime.pipeline import PRIORS
from como3r.viewer import MODES as VIEWER_MODES

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: every Markdown file of the project's documentation: the README and the manual's pages
DOCUMENTS = [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]
#: the page with the synopsis of every command
COMMANDS_PAGE = DOCS / "commands" / "index.md"
GROUP = "como3r"
#: option -> the values the code accepts, for options whose values are words
CHOICES = {
    "--prior": set(PRIORS),
    "--precision": set(PRECISIONS),
    "--odometry": {*ODOMETRY_PRESETS, "none"},
    "--mode": {"centralized", "decentralized"},
    "--device": {"cpu", "cuda"},
    "--format": set(FORMATS),
    "--viewer": set(VIEWER_MODES),
    "--preset": set(PRESETS),
}


def _name(path: Path) -> str:
    return str(path.relative_to(ROOT))


# --- the CLI --------------------------------------------------------------------------


def _cli_commands() -> dict[str, set[str]]:
    """Command path (``run``, ``weights fetch``, ``como3r`` for the group) -> the option
    names click knows for it (``--help`` aside)."""
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


def _subcommands() -> dict[str, set[str]]:
    """Group path (``como3r``, ``weights``, ``team``) -> the names of its commands."""
    root = typer.main.get_command(app)
    found: dict[str, set[str]] = {}

    def walk(group, prefix: list[str]) -> None:
        found[" ".join(prefix) or GROUP] = set(group.commands)
        for name, command in group.commands.items():
            if hasattr(command, "commands"):
                walk(command, [*prefix, name])

    walk(root, [])
    return found


CLI = _cli_commands()
GROUPS = _subcommands()


# --- commands shown in the documents ----------------------------------------------------

_FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)


def _shown_commands(text: str) -> list[str]:
    """Every ``como3r ...`` command a document shows: each line of its code blocks (a
    trailing ``\\`` continues a line; ``# comments`` dropped; ``&&``, ``;`` and `` | ``
    separate commands) and each inline code span, that starts with ``como3r``."""
    lines: list[str] = []
    for block in _FENCE.findall(text):
        lines += re.sub(r"\\\n\s*", " ", block).splitlines()
    lines = [re.sub(r"(^|\s)#.*$", "", line) for line in lines]
    prose = _FENCE.sub("", text)
    lines += re.findall(r"(?<!`)`([^`\n]+)`(?!`)", prose)
    commands = []
    for line in lines:
        for segment in re.split(r"&&|;| \| ", line):
            segment = " ".join(segment.split()).removeprefix("$ ")
            if segment == GROUP or segment.startswith(GROUP + " "):
                commands.append(segment)
    return commands


def _words(command: str) -> list[str]:
    """The command's words, brackets and parentheses of a synopsis taken off."""
    return [w for w in re.split(r"[\s\[\]()]+", command) if w]


def _command_path(words: list[str]) -> tuple[str, list[str], str | None]:
    """(command path, the words after it, a problem or None) of ``como3r``'s arguments."""
    rest = [w for w in words[1:]]
    while rest and rest[0] in ("-v", "--verbose", "-v|--verbose"):
        rest = rest[1:]
    path: list[str] = []
    while rest and " ".join(path or [GROUP]) in GROUPS:
        group = " ".join(path) or GROUP
        if rest[0] in GROUPS[group]:
            path.append(rest.pop(0))
        elif re.fullmatch(r"[a-z]+", rest[0]):
            return group, rest, f"{group!r} has no command {rest[0]!r}"
        else:
            break
    return " ".join(path) or GROUP, rest, None


def _problems(command: str) -> list[str]:
    """What in ``command`` the CLI does not accept: an unknown command or option, a value
    not among an option's choices, a ``--set`` key that is not in the configuration."""
    path, rest, problem = _command_path(_words(command))
    if problem:
        return [problem]
    if path in GROUPS and path != GROUP and not rest:
        return []  # a group named in prose, e.g. `como3r weights`
    known = CLI.get(path)
    if known is None:
        return [f"{path!r} is a group: name one of its commands {sorted(GROUPS[path])}"]
    found = []
    for i, word in enumerate(rest):
        for piece in word.split("|"):
            option = re.fullmatch(r"(--?[a-z][a-z0-9-]*)(=.*)?", piece)
            if option is None:
                continue
            if option.group(1) not in known | {"--help"}:
                found.append(f"{path}: no option {option.group(1)}")
                continue
            value = rest[i + 1] if i + 1 < len(rest) and "|" not in word else None
            if value is None:
                continue
            if option.group(1) in CHOICES:
                listed = set(value.split("|"))
                if all(re.fullmatch(r"[a-z0-9-]+", v) for v in listed):
                    wrong = listed - CHOICES[option.group(1)]
                    if wrong:
                        found.append(f"{path}: {option.group(1)} does not take {sorted(wrong)}")
            if option.group(1) == "--set" and re.fullmatch(r"[a-z_]+(\.[a-z_]+)+=.*", value):
                try:
                    apply_overrides(Config(), [value])
                except ConfigError as error:
                    found.append(f"{path}: --set {value}: {error}")
    return found


@pytest.mark.parametrize("document", DOCUMENTS, ids=_name)
def test_every_command_shown_is_one_the_cli_accepts(document: Path) -> None:
    commands = _shown_commands(document.read_text())
    problems = [f"{c!r}: {p}" for c in commands for p in _problems(c)]
    assert not problems, f"{_name(document)}:\n" + "\n".join(problems)


def test_the_command_check_catches_what_it_should() -> None:
    assert _problems("como3r run --agent a --out b --prior simulated") == []
    assert _problems("como3r weights fetch --trust-unverified") == []
    assert _problems("como3r run --agnt a")
    assert _problems("como3r runn --agent a")
    assert _problems("como3r run --prior dust3r")
    assert _problems("como3r run --set tracking.no_such_key=1")
    assert _problems("como3r weights fecth")
    shown = _shown_commands(
        "x `como3r eval --est a` y\n```\n$ como3r demo \\\n  --out d  # c\n```\n"
    )
    assert shown == ["como3r demo --out d", "como3r eval --est a"]


def test_the_documents_show_commands() -> None:
    """The check above is not vacuous: the manual shows commands of every kind."""
    shown = {_command_path(_words(c))[0] for d in DOCUMENTS for c in _shown_commands(d.read_text())}
    assert set(CLI) - {GROUP} <= shown


# --- the synopsis ---------------------------------------------------------------------


def _synopsis() -> str:
    """The first code block of the commands page."""
    block = _FENCE.search(COMMANDS_PAGE.read_text())
    assert block is not None, f"{_name(COMMANDS_PAGE)} has no code block"
    return block.group(1)


def _synopsis_commands() -> dict[str, str]:
    """Command path -> its synopsis text, continuation lines included."""
    commands: dict[str, str] = {}
    current = None
    for line in _synopsis().splitlines():
        if line.startswith(GROUP):
            current = _command_path(_words(line))[0]
            commands[current] = line
        elif line.strip() and current is not None:
            commands[current] += " " + line.strip()
    return commands


def _options(synopsis: str) -> set[str]:
    return set(re.findall(r"(?<![\w-])(--?[a-z][a-z0-9-]*)", synopsis))


def test_every_command_is_in_the_synopsis_and_no_other() -> None:
    assert sorted(_synopsis_commands()) == sorted(CLI)


@pytest.mark.parametrize("command", sorted(CLI))
def test_the_synopsis_lists_exactly_the_options_of(command: str) -> None:
    documented = _options(_synopsis_commands().get(command, ""))
    assert documented == CLI[command], (
        f"synopsis of {command!r}: missing {sorted(CLI[command] - documented)}"
        f", not in the CLI {sorted(documented - CLI[command])}"
    )


@pytest.mark.parametrize("option", sorted(set(CHOICES) - {"--preset"}))
def test_listed_choices_are_the_accepted_ones(option: str) -> None:
    listed = re.search(rf"{option} ([a-z0-9]+(?:\|[a-z0-9]+)+)", _synopsis())
    assert listed is not None, f"{option} lists no choices in the synopsis"
    assert set(listed.group(1).split("|")) == CHOICES[option]


@pytest.mark.parametrize("command", sorted(set(CLI) - {GROUP}))
def test_each_command_has_its_page_with_its_synopsis(command: str) -> None:
    """A command's page opens with its lines of the synopsis, word for word."""
    pages = [p for p in sorted((DOCS / "commands").glob("*.md")) if p != COMMANDS_PAGE]
    lines = [
        line
        for line in _synopsis().splitlines()
        if line.strip() and not line.startswith(GROUP + " [")
    ]
    owning = [p for p in pages if f"como3r {command}" in _synopsis_of_page(p)]
    assert owning, f"no page under docs/commands/ shows the synopsis of {command!r}"
    assert all(line in _synopsis() for line in _synopsis_of_page(owning[0]).splitlines()), lines


def _synopsis_of_page(page: Path) -> str:
    block = _FENCE.search(page.read_text())
    return block.group(1) if block else ""


def test_the_preset_list_names_every_preset() -> None:
    text = (DOCS / "commands" / "synth.md").read_text()
    paragraph = re.search(r"^Synthetic presets: (.*?)(?:\n\n|\n?\Z)", text, re.S | re.M)
    assert paragraph is not None
    assert set(re.findall(r"`([a-z-]+)`", paragraph.group(1))) == set(PRESETS)


# --- links and pages ------------------------------------------------------------------


@pytest.mark.parametrize("document", DOCUMENTS, ids=_name)
def test_relative_links_resolve(document: Path) -> None:
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", document.read_text())
    relative = [t for t in targets if "://" not in t and not t.startswith("mailto:")]
    missing = [t for t in relative if not (document.parent / t).exists()]
    assert not missing, f"{_name(document)} links to missing files: {missing}"


def test_the_architecture_document_names_every_package() -> None:
    text = (DOCS / "architecture.md").read_text()
    packages = sorted(
        p.name for p in (ROOT / "src" / "como3r").iterdir() if (p / "__init__.py").exists()
    )
    assert packages, "no sub-packages found under src/como3r"
    assert [p for p in packages if f"`{p}/`" not in text] == []


def _resolve(name: str) -> None:
    """Import the longest importable module prefix of ``name``, then get the rest."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            found = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for part in parts[i:]:
            found = getattr(found, part)
        return
    raise ImportError(name)


@pytest.mark.parametrize("document", DOCUMENTS, ids=_name)
def test_the_code_the_documents_name_exists(document: Path) -> None:
    """A module, class or function named in code (`como3r.data.poses.MAX_GAP`) imports, and a
    file named by its path (`src/como3r/...`, `benchmarks/...`) exists: a move or a rename
    shows here."""
    text = document.read_text()
    spans = re.findall(r"`([^`\n]+)`", text)
    names = {m for s in spans for m in re.findall(r"(?<![\w/.])como3r(?:\.[A-Za-z_]\w*)+", s)}
    unresolved = []
    for name in sorted(names):
        try:
            _resolve(name)
        except (ImportError, AttributeError):
            unresolved.append(name)
    paths = re.findall(r"`((?:src|tests|benchmarks|scripts|docs)/[\w/.-]+)`", text)
    missing = [p for p in paths if not (ROOT / p).exists()]
    assert not unresolved and not missing, f"{_name(document)}: {unresolved} {missing}"


def test_the_name_check_catches_what_it_should() -> None:
    _resolve("como3r.data.poses.MAX_GAP")
    with pytest.raises(AttributeError):
        _resolve("como3r.data.poses.NO_SUCH_NAME")
    with pytest.raises(ImportError):
        _resolve("como3r_no_such_package.x")


def test_the_manual_names_nothing_from_the_shared_folder() -> None:
    """Users have no /work/shared: the manual's examples use public downloads."""
    assert [d for d in DOCUMENTS if "/work/shared" in d.read_text()] == []


# --- the configuration reference ------------------------------------------------------


def _hook():
    spec = importlib.util.spec_from_file_location(
        "config_reference", DOCS / "hooks" / "config_reference.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_the_configuration_reference_has_every_key_with_its_default() -> None:
    text = _hook().render()
    listed = dict(re.findall(r"^- \*\*`([\w.]+)`\*\* \(`[^`]*`, default `([^`]*)`\)", text, re.M))
    keys = _flatten(config_to_dict(Config()))
    assert sorted(listed) == sorted(keys)
    for key, value in keys.items():
        assert listed[key] in (repr(value), f'"{value}"'), key


def test_the_configuration_reference_takes_each_kind_of_field_documentation() -> None:
    docs = {f.key: f.doc for s in _hook().sections() for f in s.fields}
    assert "fraction of the query point's range" in docs["matching.occlusion_ratio"]  # Attributes:
    assert "MASt3R-SLAM: below this" in docs["tracking.min_match_fraction"]  # comment after
    assert "the keyframe's first prediction" in docs["depth.refine_from"]  # comment above
    assert "pages out" not in docs["session.spill_dir"]  # ``name``: paragraphs, each its own
    assert "temporary folder" in docs["session.spill_dir"]
    assert "log-depth" in docs["tracking.sigma_depth"]  # a block above names another field


SAMPLE_CONFIG = '''
from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class Inner:
    """The inner section.

    Attributes:
        listed: documented in Attributes,
            over two lines.
    """

    listed: float = 0.5
    plain: int = 3


@dataclass(frozen=True)
class Outer:
    """The root.

    ``para``: documented by a paragraph.
    """

    # documented above,
    # over two lines
    above: str = "x"
    after: bool = True  # documented after
    attribute: Literal["a", "b"] = "b"
    """documented by an attribute docstring"""
    para: float = 1.0
    inner: Inner = field(default_factory=Inner)
'''


def test_the_configuration_reference_reads_every_way_a_field_is_documented(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "sample_config.py").write_text(SAMPLE_CONFIG)
    monkeypatch.syspath_prepend(str(tmp_path))
    outer = importlib.import_module("sample_config").Outer
    found = {f.key: (f.type, f.default, f.doc) for s in _hook().sections(outer) for f in s.fields}
    assert found == {
        "above": ("str", '"x"', "documented above, over two lines"),
        "after": ("bool", "True", "documented after"),
        "attribute": ('"a" | "b"', '"b"', "documented by an attribute docstring"),
        "para": ("float", "1.0", "``para``: documented by a paragraph."),
        "inner.listed": ("float", "0.5", "documented in Attributes, over two lines."),
        "inner.plain": ("int", "3", ""),
    }
    text = _hook().render(outer)
    assert "### `inner`" in text and "`Inner`: The inner section." in text


def test_the_configuration_page_holds_the_generated_reference() -> None:
    assert _hook().MARKER in (DOCS / "configuration.md").read_text()


# --- the site -------------------------------------------------------------------------


def test_mkdocs_builds_the_manual_strictly(tmp_path: Path) -> None:
    """Warnings (a broken link or anchor, a page outside the navigation, an API page that
    does not resolve) fail the build."""
    site = tmp_path / "site"
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert result.returncode == 0, result.stdout + result.stderr
    page = (site / "configuration" / "index.html").read_text()
    assert "decentralized.pose_graph.scale_alarm_log" in page
    assert "config-reference" not in page
    assert (site / "api" / "geometry" / "index.html").exists()
    assert "se3_exp" in (site / "api" / "geometry" / "index.html").read_text()
    assert (site / "assets" / "front_map.png").is_file()
    assert not (site / "hooks").exists() and not (site / "assets" / "front_map.py").exists()

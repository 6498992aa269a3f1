"""The README is the front page (issue 40): short, with the picture, the install, the demo, a
real sequence (with and without MASt3R's weights), the test command and links into the
manual, each of which resolves to one of the manual's pages. Every command it shows is
checked against the CLI with the manual's (tests/test_docs.py)."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: the most lines the front page may have
MAX_LINES = 200
#: the most bytes its picture may have
MAX_PICTURE_BYTES = 200_000


def _text() -> str:
    return README.read_text()


def _links() -> list[str]:
    """The README's relative link targets, anchors dropped."""
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", _text())
    return [t for t in targets if "://" not in t]


def _nav_pages() -> set[str]:
    """The pages of mkdocs.yml's navigation, relative to its docs_dir."""
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    pages: set[str] = set()

    def walk(entry) -> None:
        if isinstance(entry, str):
            pages.add(entry)
        elif isinstance(entry, list):
            for item in entry:
                walk(item)
        elif isinstance(entry, dict):
            for value in entry.values():
                walk(value)

    walk(config["nav"])
    return {f"{config['docs_dir']}/{page}" for page in pages}


def test_the_readme_is_a_front_page() -> None:
    assert len(_text().splitlines()) <= MAX_LINES


def test_the_readme_links_into_the_manual_and_each_link_is_a_page() -> None:
    pages = [t for t in _links() if t.endswith(".md")]
    assert "docs/index.md" in pages and "docs/configuration.md" in pages
    # a link is a page of the manual, or one of the repository's own files beside the README
    repository_files = {"CONTRIBUTING.md", "CHANGELOG.md"}
    assert [p for p in pages if p not in _nav_pages() | repository_files] == []
    assert all((ROOT / p).is_file() for p in pages if p in repository_files)


def test_the_readme_links_every_part_of_the_manual() -> None:
    """Every top-level entry of the site's navigation (a section by its first page)."""
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    firsts = []
    for entry in config["nav"]:
        value = next(iter(entry.values())) if isinstance(entry, dict) else entry
        while isinstance(value, list):
            value = value[0]
        if isinstance(value, dict):
            value = next(iter(value.values()))
        firsts.append(f"{config['docs_dir']}/{value}")
    assert [page for page in firsts if page not in _links()] == []


def test_the_readme_links_the_architecture_document() -> None:
    assert "(docs/architecture.md)" in _text()


def test_the_readme_shows_a_small_picture_of_a_merged_map() -> None:
    pictures = re.findall(r"!\[[^\]]+\]\(([^)]+\.png)\)", _text())
    assert pictures, "the README shows no picture"
    for picture in pictures:
        assert (ROOT / picture).is_file(), picture
        assert (ROOT / picture).stat().st_size < MAX_PICTURE_BYTES, picture


def test_the_readme_shows_install_demo_and_a_real_sequence_with_and_without_weights() -> None:
    text = _text()
    assert "bash scripts/install.sh" in text
    assert re.search(r"^como3r demo ", text, re.M)
    assert re.search(r"^como3r weights fetch", text, re.M)
    real = re.findall(r"^como3r run --agent (\S+) .*$", text, re.M)
    assert real and all("freiburg" in agent for agent in real), real
    assert re.search(r"^como3r run --agent \S+ .*--prior simulated", text, re.M)
    assert re.search(r"^como3r eval --est ", text, re.M)


def test_the_test_command_is_between_its_markers() -> None:
    block = re.search(
        r"^<!-- test-command -->\n```\n(.+?)\n```\n<!-- /test-command -->$", _text(), re.S | re.M
    )
    assert block is not None and "pytest" in block.group(1)

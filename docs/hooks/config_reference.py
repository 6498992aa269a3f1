"""MkDocs hook: the configuration reference, generated from the config dataclasses.

A page holding the line ``<!-- config-reference -->`` gets it in that line's place when the
site is built, so the reference cannot drift from the code: every key of
:class:`como3r.config.Config` (sections and nested sections followed from the root), its
type and default as the dataclasses give them, and its documentation as the source writes
it, wherever that is:

- a comment block right above the field, or a comment after it on its line;
- a string right after the field (an attribute docstring);
- an entry of the class docstring's ``Attributes:`` section (``name, other: text``);
- a paragraph or ``*`` item of the class docstring that starts with the field's name in
  double backticks (``min_covisible_ratio``: ...).

The rest of a class docstring introduces its section. The classes are found by importing
:mod:`como3r.config` from this checkout's ``src/`` and their source by parsing the files
that define them (:mod:`ast`), so the reference follows a class that moves.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import re
import sys
import textwrap
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: the line a page writes where the reference goes
MARKER = "<!-- config-reference -->"
SRC = Path(__file__).resolve().parents[2] / "src"


@dataclass
class FieldDoc:
    """One key of the configuration: ``key`` dotted from the root."""

    key: str
    type: str
    default: str
    doc: str


@dataclass
class SectionDoc:
    """One dataclass of the tree: its dotted ``key`` ("" for the root), its introduction."""

    key: str
    cls: type
    intro: str
    fields: list[FieldDoc] = field(default_factory=list)


def _root() -> type:
    if str(SRC) not in sys.path:
        sys.path.insert(0, str(SRC))
    return importlib.import_module("como3r.config").Config


def _class_node(cls: type) -> tuple[ast.ClassDef, list[str]]:
    """The ``class`` statement of ``cls`` and the lines of its file."""
    path = inspect.getsourcefile(cls)
    assert path is not None, f"no source file for {cls.__qualname__}"
    source = Path(path).read_text()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ClassDef) and node.name == cls.__name__:
            return node, source.splitlines()
    raise LookupError(f"class {cls.__name__} not found in {path}")


def _comments(node: ast.ClassDef, lines: list[str]) -> dict[str, str]:
    """Field name -> the comment block above its line and the comment after it."""
    found: dict[str, str] = {}
    names = {
        s.target.id
        for s in node.body
        if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)
    }
    previous_end = node.body[0].end_lineno if node.body else node.lineno
    previous: ast.stmt | None = None
    for statement in node.body:
        if (
            isinstance(previous, ast.AnnAssign)
            and isinstance(previous.target, ast.Name)
            and isinstance(statement, ast.Expr)
            and isinstance(statement.value, ast.Constant)
            and isinstance(statement.value.value, str)
        ):  # an attribute docstring: the string right after the field
            name = previous.target.id
            text = " ".join(inspect.cleandoc(statement.value.value).split())
            found[name] = f"{found.get(name, '')} {text}".strip()
        previous = statement
        if not (isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)):
            previous_end = statement.end_lineno or statement.lineno
            continue
        above: list[str] = []
        number = statement.lineno - 2  # 0-based index of the line above
        while number >= previous_end and lines[number].strip().startswith("#"):
            above.insert(0, lines[number].strip().lstrip("#").strip())
            number -= 1
        for name, text in _split_by_name(above, names, statement.target.id).items():
            found[name] = f"{found.get(name, '')} {text}".strip()
        last = lines[(statement.end_lineno or statement.lineno) - 1]
        after = re.search(r"\s+#\s?(.*)$", last) if "#" in last else None
        if after and not _inside_string(last, after.start()):
            name = statement.target.id
            found[name] = f"{found.get(name, '')} {after.group(1).strip()}".strip()
        previous_end = statement.end_lineno or statement.lineno
    return found


def _split_by_name(block: list[str], names: set[str], below: str) -> dict[str, str]:
    """A comment block's lines by the field they describe: a line that starts with another
    field's name (``sigma_depth (C-Eq. 17 ...``, ``sigma_dist: ...``) begins that field's
    part, the rest is the field below the block."""
    parts: dict[str, list[str]] = {}
    current = below
    for line in block:
        lead = re.match(r"(\w+)(?::| \()", line)
        if lead and lead.group(1) in names:
            current = lead.group(1)
        parts.setdefault(current, []).append(line)
    return {name: " ".join(text) for name, text in parts.items()}


def _inside_string(line: str, position: int) -> bool:
    """Whether ``position`` of ``line`` lies inside a quoted string (a ``#`` in a default)."""
    quotes = [c for c in line[:position] if c in "\"'"]
    return len(quotes) % 2 == 1


def _docstring_parts(cls: type, names: set[str]) -> tuple[str, dict[str, str]]:
    """The class docstring split into its introduction and the text it gives each field."""
    text = inspect.cleandoc(cls.__doc__ or "")
    per_field: dict[str, str] = {}
    intro: list[str] = []
    blocks = re.split(r"\n\s*\n", text)
    for block in blocks:
        if block.startswith("Attributes:"):
            entries = re.split(r"\n(?=\S)", textwrap.dedent(block[len("Attributes:") :]).strip())
            for entry in entries:
                head = re.match(r"([\w, ]+):\s", entry)
                if not head:
                    continue
                keys = [k.strip() for k in head.group(1).split(",")]
                body = " ".join(entry[head.end() :].split())
                for key in keys:
                    if key in names:
                        per_field[key] = body
            continue
        items = re.split(r"\n(?=\* )", block) if block.lstrip().startswith("* ") else [block]
        kept: list[str] = []
        for item in items:
            flat = " ".join(item.split())
            lead = re.match(r"(?:\* )?``(\w+)``", flat)
            if lead and lead.group(1) in names:
                body = flat[2:] if flat.startswith("* ") else flat
                per_field[lead.group(1)] = (per_field.get(lead.group(1), "") + " " + body).strip()
            else:
                kept.append(item)
        if kept:
            intro.append("\n".join(kept))
    return "\n\n".join(intro), per_field


def _type_name(hint: Any) -> str:
    if typing.get_origin(hint) is typing.Literal:
        return " | ".join(
            f'"{a}"' if isinstance(a, str) else repr(a) for a in typing.get_args(hint)
        )
    return getattr(hint, "__name__", str(hint).replace("typing.", ""))


def _default(value: Any) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


def sections(root: type | None = None) -> list[SectionDoc]:
    """Every dataclass of the configuration tree under ``root`` (default
    :class:`como3r.config.Config`), the root first, depth first."""
    found: list[SectionDoc] = []

    def visit(cls: type, key: str) -> None:
        node, lines = _class_node(cls)
        fields = dataclasses.fields(cls)
        names = {f.name for f in fields}
        intro, documented = _docstring_parts(cls, names)
        commented = _comments(node, lines)
        section = SectionDoc(key=key, cls=cls, intro=intro)
        found.append(section)
        hints = typing.get_type_hints(cls)
        instance = cls()
        nested: list[tuple[type, str]] = []
        for f in fields:
            dotted = f"{key}.{f.name}" if key else f.name
            hint = hints[f.name]
            if dataclasses.is_dataclass(hint):
                nested.append((hint, dotted))
                continue
            doc = " ".join(p for p in (commented.get(f.name), documented.get(f.name)) if p)
            section.fields.append(
                FieldDoc(dotted, _type_name(hint), _default(getattr(instance, f.name)), doc)
            )
        for child, dotted in nested:
            visit(child, dotted)

    visit(root or _root(), "")
    return found


def _markdown_text(text: str) -> str:
    """Docstring markup as Markdown: ``code`` to `code`, Sphinx roles to their target."""
    text = re.sub(r":(?:mod|func|class|meth|data|attr):`~?\.?([^`]+)`", r"`\1`", text)
    text = re.sub(r"``([^`]+)``", r"`\1`", text)
    return re.sub(r"(?<![`\w])\*(?=\w)", r"\\*", text)  # a lone * is not emphasis


def render(root: type | None = None) -> str:
    """The reference as Markdown: one heading per section, one item per key."""
    out: list[str] = []
    for section in sections(root):
        title = f"`{section.key}`" if section.key else "Top level"
        out += [
            f"### {title}",
            "",
            f"`{section.cls.__name__}`: {_markdown_text(section.intro)}",
            "",
        ]
        for f in section.fields:
            line = f"- **`{f.key}`** (`{f.type}`, default `{f.default}`)"
            out.append(f"{line}: {_markdown_text(f.doc)}" if f.doc else line)
        out.append("")
    return "\n".join(out)


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    """MkDocs event: put the reference in place of :data:`MARKER`."""
    if MARKER not in markdown:
        return markdown
    return markdown.replace(MARKER, render())

"""A Griffe extension that renders torchdeform's reStructuredText-flavoured docstrings as Markdown.

The library's docstrings are Google style with a few reStructuredText habits that read well in
``help()`` and in an editor: ``:class:`Name``` roles, ````code```` literals, ``Example:``
sections, simple tables (rows between ``====  ====`` rules) and literal blocks introduced by
``::``. MkDocs renders Markdown, so this extension rewrites those constructs, in memory, before
Griffe parses a docstring (the source files are untouched):

- ``:role:`~a.b.c``` becomes ```c``` and ``:role:`a.b``` becomes ```a.b``` (code, no link: a
  link would have to resolve under ``mkdocs build --strict`` for every module-level name);
- an ``Example:`` section becomes ``Examples:``, which Griffe parses into code blocks;
- a simple table becomes a bullet list (first column, then the rest of the row);
- a paragraph ending in ``::`` keeps one ``:`` and its indented block becomes a fenced block.

Loaded by ``mkdocs.yml`` (``plugins.mkdocstrings.handlers.python.options.extensions``).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|exc|obj|const|ref|term):`(~?)([^`]+)`")
RULE = re.compile(r"^(\s*)(=+)((?: +=+)+)\s*$")
EXAMPLE = re.compile(r"^(\s*)Example:\s*$", re.M)


def _role(match: re.Match) -> str:
    tilde, target = match.groups()
    target = target.strip()
    if "<" in target and target.endswith(">"):  # :ref:`text <target>`
        target = target.split("<")[0].strip()
    if tilde or target.startswith("."):
        target = target.lstrip(".").split(".")[-1] if tilde else target.lstrip(".")
    return f"`{target}`"


def _columns(rule: str) -> list[tuple[int, int]]:
    return [(m.start(), m.end()) for m in re.finditer(r"=+", rule)]


def _tables(lines: list[str]) -> list[str]:
    """Simple tables (three rules: top, optional header separator, bottom) -> bullet lists."""
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = RULE.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        indent = m.group(1)
        spans = _columns(lines[i])
        rows: list[list[str]] = []
        j = i + 1
        while j < len(lines) and not RULE.match(lines[j]):
            line = lines[j]
            if line.strip():
                cells = [
                    line[a : (spans[k + 1][0] if k + 1 < len(spans) else None)].strip()
                    for k, (a, _) in enumerate(spans)
                ]
                if cells[0] or not rows:
                    rows.append(cells)
                else:  # a continuation line: its cells extend the row above
                    rows[-1] = [f"{p} {c}".strip() for p, c in zip(rows[-1], cells)]
            j += 1
        out.append("")
        for cells in rows:
            first, rest = cells[0], " ".join(c for c in cells[1:] if c)
            out.append(f"{indent}- {first}: {rest}" if rest else f"{indent}- {first}")
        out.append("")
        i = j + 1
    return out


def _literal_blocks(lines: list[str]) -> list[str]:
    """A line ending in ``::`` followed by an indented block -> the line with ``:`` and a fence."""
    out: list[str] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.rstrip().endswith("::") and not line.strip().startswith(">>>"):
            base = len(line) - len(line.lstrip())
            j = i + 1
            while j < len(lines) and not lines[j].strip():
                j += 1
            block_start = j
            while j < len(lines) and (not lines[j].strip() or len(lines[j]) - len(lines[j].lstrip()) > base):
                j += 1
            while j > block_start and not lines[j - 1].strip():
                j -= 1
            if j > block_start:
                stripped = line.rstrip()[:-1]
                out.append(stripped if stripped.strip() != ":" else "")
                pad = " " * base
                out += ["", f"{pad}```text"]
                inner = min(len(x) - len(x.lstrip()) for x in lines[block_start:j] if x.strip())
                out += [pad + x[inner:] if x.strip() else "" for x in lines[block_start:j]]
                out += [f"{pad}```", ""]
                i = j
                continue
        out.append(line)
        i += 1
    return out


def to_markdown(text: str) -> str:
    """The Markdown form of one docstring (see the module docstring for the rules)."""
    text = EXAMPLE.sub(r"\1Examples:", text)
    lines = _literal_blocks(_tables(text.splitlines()))
    code = False
    for k, line in enumerate(lines):
        if line.strip().startswith("```"):
            code = not code
        elif not code and not line.lstrip().startswith((">>>", "...")):
            lines[k] = ROLE.sub(_role, line)
    return "\n".join(lines)


class RstToMarkdown(griffe.Extension):
    """Rewrite every docstring of the loaded objects before it is parsed."""

    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:  # noqa: D102
        if obj.docstring is not None:
            obj.docstring.value = to_markdown(obj.docstring.value)

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:  # noqa: D102
        # the top-level package itself is not among the objects on_object sees
        self.on_object(obj=pkg)

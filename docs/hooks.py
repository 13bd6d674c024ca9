"""MkDocs hooks: pages generated at build time from the library's own sources.

- ``<!-- scene-keys -->`` becomes the scene-file reference: the ``Keys`` section of the module
  docstring of ``torchdeform/scene/__init__.py``, one heading per section. The keys are written
  once, in that docstring (which ``help(torchdeform.scene)`` shows too).
- ``<!-- top-level-names -->`` becomes the table of the names ``import torchdeform as td`` offers,
  each linked to the subpackage page that documents it, from ``torchdeform/__init__.py``.

Both read the source files with :mod:`ast` (no import of torch), so they cost milliseconds.
"""

from __future__ import annotations

import ast
import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "torchdeform"

_spec = importlib.util.spec_from_file_location("griffe_rst", Path(__file__).with_name("griffe_rst.py"))
_rst = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_rst)

#: where each top-level module's names are documented (see mkdocs.yml's nav)
_GROUND_FLOOR = ("errors", "options", "outputs", "checks")


def _docstring(path: Path) -> str:
    return ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")), clean=True) or ""


def _sentence(text: str) -> str:
    """``(required)`` -> ``Required.``; ``(optional): a part ...`` -> ``Optional. A part ....``."""
    if text.startswith("("):
        depth = 0
        for i, ch in enumerate(text):
            depth += {"(": 1, ")": -1}.get(ch, 0)
            if depth == 0:
                inner, after = text[1:i], text[i + 1 :].lstrip(":").strip()
                break
        else:
            inner, after = text, ""
        parts = [p for p in (inner, after) if p]
        return " ".join(p[0].upper() + p[1:] + ("" if p.endswith(".") else ".") for p in parts)
    return text[0].upper() + text[1:]


def scene_keys() -> str:
    """The ``Keys`` section of ``torchdeform.scene``'s docstring as Markdown, one heading per section."""
    doc = _docstring(PACKAGE / "scene" / "__init__.py")
    m = re.search(r"^Keys\n-+\n(.*?)(?=^Every problem|^Modules:|\Z)", doc, re.M | re.S)
    if not m:
        raise ValueError("torchdeform/scene/__init__.py: its docstring has no 'Keys' section (scene-file reference)")
    paragraphs = re.split(r"\n\s*\n", m.group(1).strip())
    out = []
    for para in paragraphs:
        text = _rst.to_markdown(para).replace("``", "`")
        head = re.match(r"`([^`]+)`", text)
        if head and not text.startswith("- ") and (head.group(1).startswith("[") or head.group(1).startswith("model")):
            rest = text[head.end() :].strip().rstrip(":")
            out.append(f"## `{head.group(1)}`\n")
            if rest:
                out.append(_sentence(rest))
        else:
            out.append(text)
    return "\n\n".join(out) + "\n"


def top_level_names() -> str:
    """A Markdown table: every name of ``torchdeform.__all__`` with the page that documents it."""
    tree = ast.parse((PACKAGE / "__init__.py").read_text(encoding="utf-8"))
    home: dict[str, str] = {}
    names: list[str] = []
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
            for alias in node.names:
                home[alias.asname or alias.name] = node.module
        elif isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            names = [ast.literal_eval(e) for e in node.value.elts]
    rows = ["| name | documented in |", "|---|---|"]
    for name in names:
        module = home.get(name)
        if module is None:
            continue
        sub = module.split(".")[0]
        page = "core.md" if sub in _GROUND_FLOOR else f"{sub}.md"
        rows.append(f"| [`td.{name}`][torchdeform.{module}.{name}] | [`torchdeform.{sub}`]({page}) |")
    return "\n".join(rows) + "\n"


def on_page_markdown(markdown: str, page, config, files) -> str:
    """Fill the generated parts of a page."""
    if "<!-- scene-keys -->" in markdown:
        markdown = markdown.replace("<!-- scene-keys -->", scene_keys())
    if "<!-- top-level-names -->" in markdown:
        markdown = markdown.replace("<!-- top-level-names -->", top_level_names())
    return markdown

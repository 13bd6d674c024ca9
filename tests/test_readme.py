"""The README stays true: every ```python block runs as written, and "Where things are" names the tree.

Each block runs on its own in a fresh Python process, as a user would paste it: nothing is
shared between blocks. The working directory is a temporary folder that links the repository's
top-level folders (``data/``, ``tests/``, ``scenes/``, ...), so paths in the README are written
relative to the repository root, as users type them, and whatever a block writes (``loss.png``,
``view.png``, ``body.stl``) lands in the temporary folder. Blocks must be fast (a few seconds on
2 cores) and must not compile: code that calls ``torch.compile`` belongs in the prose.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
README = ROOT / "README.md"
PACKAGE = ROOT / "torchdeform"
TIMEOUT_S = 120
FENCE = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.M | re.S)
COMPILES = re.compile(r"torch\.compile|compiled_step|\.compiled\(|engine\s*=\s*[\"']compiled")


def python_blocks() -> list[str]:
    """The ```python blocks of the README, in order (the fence exactly ```python at a line start)."""
    return FENCE.findall(README.read_text(encoding="utf-8"))


def block_id(index: int, source: str) -> str:
    first = next((line.strip() for line in source.splitlines() if line.strip()), "")
    return f"{index}: {first[:60]}"


BLOCKS = python_blocks()


def test_readme_has_python_blocks():
    assert BLOCKS, f"no ```python blocks found in {README}"


@pytest.mark.parametrize("index, source", list(enumerate(BLOCKS)), ids=[block_id(i, b) for i, b in enumerate(BLOCKS)])
def test_readme_block_runs(index, source, tmp_path):
    assert not COMPILES.search(source), (
        f"README python block {index} compiles (torch.compile costs 20-60 s per shape): "
        "show compiling code in the prose, not in a ```python block"
    )
    work = tmp_path / "work"
    work.mkdir()
    for entry in ROOT.iterdir():  # data/, tests/, scenes/, ...: README paths from the root
        if (
            entry.is_dir()
            and not entry.name.startswith((".", "_"))
            and entry.name != PACKAGE.name
            and not entry.name.endswith(".egg-info")
        ):
            (work / entry.name).symlink_to(entry, target_is_directory=True)
    script = tmp_path / f"readme_block_{index}.py"  # outside the working folder: a clean sys.path[0]
    script.write_text(source, encoding="utf-8")
    env = dict(
        os.environ,
        MPLBACKEND="Agg",
        PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    )
    try:
        proc = subprocess.run(
            [sys.executable, str(script)], cwd=work, env=env, capture_output=True, text=True, timeout=TIMEOUT_S
        )
    except subprocess.TimeoutExpired as e:  # captured output is bytes here, whatever text= says
        err = e.stderr.decode(errors="replace") if isinstance(e.stderr, bytes) else e.stderr or ""
        pytest.fail(
            f"README python block {index} ran longer than {TIMEOUT_S} s (blocks must take a few "
            f"seconds)\n--- block ---\n{source}\n--- stderr ---\n{err[-4000:]}"
        )
    assert proc.returncode == 0, (
        f"README python block {index} failed with exit status {proc.returncode}\n"
        f"--- block ---\n{source}\n--- stdout ---\n{proc.stdout[-2000:]}\n--- stderr ---\n{proc.stderr[-6000:]}"
    )


def where_things_are() -> str:
    text = README.read_text(encoding="utf-8")
    m = re.search(r"^## Where things are[ \t]*\n(.*?)(?=^## |\Z)", text, re.M | re.S)
    assert m, "README.md has no '## Where things are' section"
    return m.group(1)


def test_where_things_are_lists_every_subpackage():
    section = where_things_are()
    subpackages = sorted(d.name for d in PACKAGE.iterdir() if (d / "__init__.py").is_file())
    assert subpackages
    missing = [name for name in subpackages if f"torchdeform/{name}/" not in section]
    assert not missing, f"'Where things are' in README.md does not list torchdeform/{{{', '.join(missing)}}}/"


def test_where_things_are_names_every_module():
    section = where_things_are()
    bullets = {
        m.group(1): m.group(2) for m in re.finditer(r"^- `torchdeform/(\w+)/`(.*?)(?=^- |\Z)", section, re.M | re.S)
    }
    missing = {}
    for name, bullet in bullets.items():
        absent = sorted(
            f.stem for f in (PACKAGE / name).glob("*.py") if not f.stem.startswith("__") and f"`{f.stem}`" not in bullet
        )
        if absent:
            missing[name] = absent
    assert not missing, f"'Where things are' in README.md does not name these modules: {missing}"


def test_where_things_are_names_only_what_exists():
    section = where_things_are()
    named = set(re.findall(r"torchdeform/([A-Za-z_]\w*(?:/|\.py))", section))
    absent = sorted(n for n in named if not (PACKAGE / n.rstrip("/")).exists())
    assert not absent, f"'Where things are' in README.md names torchdeform/{absent} that do not exist"
    folders = set(re.findall(r"^- `([a-z]\w*)/`", section, re.M))
    absent = sorted(f for f in folders if not (ROOT / f).is_dir())
    assert not absent, f"'Where things are' in README.md names top-level folders {absent} that do not exist"

"""The README and the documentation stay true: their code runs, their scene files load, their layout is the tree.

- Every ```python block of ``README.md`` and ``docs/**/*.md`` runs on its own in a fresh Python
  process, as a user would paste it: nothing is shared between blocks (each process is forked from
  one that has imported torch and torchdeform and done nothing else, so that the 1-2 s import is
  paid once per test worker, not once per block). The working directory is a
  temporary folder that links the repository's top-level folders (``data/``, ``tests/``,
  ``scenes/``, ...), so paths in the pages are written relative to the repository root, as users
  type them, and whatever a block writes (``loss.png``, ``view.png``, ``body.stl``) lands in the
  temporary folder. Blocks must be fast (a few seconds on 2 cores) and must not compile: code that
  calls ``torch.compile`` belongs in the prose.
- Every ```toml block is a whole scene file, loaded with :func:`torchdeform.load_scene` from the
  same kind of temporary folder, unless its first line is a ``# fragment`` comment (sections of a
  scene file shown on their own), which is only parsed as TOML.
- ``README.md``'s "Where things are" names every subpackage of ``torchdeform/`` and only folders
  that exist; ``docs/layout.md`` names every module of every subpackage, and only what exists.
- No page tells the project's development history (numbered issues, sessions or rounds of work).

The oracle is the library itself (the blocks' own prints and a clean exit) and the file tree.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
README = ROOT / "README.md"
DOCS = ROOT / "docs"
LAYOUT = DOCS / "layout.md"
PACKAGE = ROOT / "torchdeform"
TIMEOUT_S = 120
PYTHON = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.M | re.S)
TOML = re.compile(r"^```toml[ \t]*\n(.*?)^```[ \t]*$", re.M | re.S)
COMPILES = re.compile(r"torch\.compile|compiled_step|\.compiled\(|engine\s*=\s*[\"']compiled")
HISTORY = re.compile(r"\b(issue|session|round) [0-9]+", re.I)


def pages() -> list[Path]:
    """README.md and every Markdown page of the documentation, in a fixed order."""
    return [README, *sorted(DOCS.rglob("*.md"))]


def blocks(fence: re.Pattern) -> list[tuple[str, str]]:
    """``(where, source)`` of every block the fence matches; ``where`` is ``page:line``."""
    found = []
    for page in pages():
        text = page.read_text(encoding="utf-8")
        for m in fence.finditer(text):
            line = text.count("\n", 0, m.start()) + 1
            found.append((f"{page.relative_to(ROOT).as_posix()}:{line}", m.group(1)))
    return found


PYTHON_BLOCKS = blocks(PYTHON)
TOML_BLOCKS = blocks(TOML)


def work_folder(tmp_path: Path) -> Path:
    """A temporary working folder that links the repository's top-level folders (not the package)."""
    work = tmp_path / "work"
    work.mkdir()
    for entry in ROOT.iterdir():
        if (
            entry.is_dir()
            and not entry.name.startswith((".", "_"))
            and entry.name not in (PACKAGE.name, "site", "build", "dist")
            and not entry.name.endswith(".egg-info")
        ):
            (work / entry.name).symlink_to(entry, target_is_directory=True)
    return work


def test_pages_have_blocks():
    assert PYTHON_BLOCKS, "no ```python blocks found in README.md and docs/"
    assert any(where.startswith("README.md") for where, _ in PYTHON_BLOCKS), "README.md has no ```python block"
    assert TOML_BLOCKS, "no ```toml blocks found in README.md and docs/"


#: the parent of every block's process: imports once, then forks a child per job read from stdin
#: (``{"script", "cwd", "out", "err", "timeout"}``) and answers ``{"status": exit status or "timeout"}``
ZYGOTE = r"""
import json, os, runpy, sys, time, traceback
import matplotlib
matplotlib.use("Agg")
import torch, torchdeform  # noqa: F401  (nothing else runs here: a fork of this process is a fresh one)
for line in sys.stdin:
    job = json.loads(line)
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            null = os.open(os.devnull, os.O_RDONLY)
            os.dup2(null, 0)
            for fd, name in ((1, "out"), (2, "err")):
                os.dup2(os.open(job[name], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644), fd)
            os.chdir(job["cwd"])
            torch.set_num_threads(1)  # the suite runs a test per core: a second thread would only spin
            sys.path[0] = os.path.dirname(job["script"])
            sys.argv = [job["script"]]
            runpy.run_path(job["script"], run_name="__main__")
            code = 0
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except BaseException:
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    deadline = time.monotonic() + job["timeout"]
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            answer = os.waitstatus_to_exitcode(status)
            break
        if time.monotonic() > deadline:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
            answer = "timeout"
            break
        time.sleep(0.005)
    print(json.dumps({"status": answer}), flush=True)
"""


@pytest.fixture(scope="module")
def zygote():
    env = dict(
        os.environ,
        MPLBACKEND="Agg",
        PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", ZYGOTE], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT
    )
    yield proc
    assert proc.stdin is not None
    proc.stdin.close()
    proc.wait(timeout=60)


def run_block(zygote, script: Path, cwd: Path) -> tuple:
    """``(exit status or "timeout", stdout, stderr)`` of ``script`` run in a fresh process forked by ``zygote``."""
    out, err = script.with_suffix(".out"), script.with_suffix(".err")
    job = {"script": str(script), "cwd": str(cwd), "out": str(out), "err": str(err), "timeout": TIMEOUT_S}
    assert zygote.stdin is not None and zygote.stdout is not None
    zygote.stdin.write(json.dumps(job) + "\n")
    zygote.stdin.flush()
    status = json.loads(zygote.stdout.readline())["status"]
    read = lambda p: p.read_text(errors="replace") if p.exists() else ""
    return status, read(out), read(err)


@pytest.mark.parametrize("where, source", PYTHON_BLOCKS, ids=[w for w, _ in PYTHON_BLOCKS])
def test_python_block_runs(where, source, tmp_path, zygote):
    assert not COMPILES.search(source), (
        f"{where}: the python block compiles (torch.compile costs 20-60 s per shape): "
        "show compiling code in the prose, not in a ```python block"
    )
    work = work_folder(tmp_path)
    script = tmp_path / "block.py"  # outside the working folder: a clean sys.path[0]
    script.write_text(source, encoding="utf-8")
    status, out, err = run_block(zygote, script, work)
    if status == "timeout":
        pytest.fail(
            f"{where}: the python block ran longer than {TIMEOUT_S} s (blocks must take a few "
            f"seconds)\n--- block ---\n{source}\n--- stderr ---\n{err[-4000:]}"
        )
    assert status == 0, (
        f"{where}: the python block failed with exit status {status}\n"
        f"--- block ---\n{source}\n--- stdout ---\n{out[-2000:]}\n--- stderr ---\n{err[-6000:]}"
    )


def test_a_failing_block_fails(tmp_path, zygote):
    """The runner can fail: a block that raises, one that exits with a status, one that prints and exits 0."""
    for source, expected in (("raise ValueError('boom')", 1), ("import sys; sys.exit(3)", 3), ("print('hi')", 0)):
        script = tmp_path / "block.py"
        script.write_text(source)
        status, out, err = run_block(zygote, script, tmp_path)
        assert status == expected, (source, status, err)
    assert "boom" not in out and out == "hi\n"


@pytest.mark.parametrize("where, source", TOML_BLOCKS, ids=[w for w, _ in TOML_BLOCKS])
def test_toml_block_loads(where, source, tmp_path):
    data = tomllib.loads(source)  # every block is valid TOML
    first = next((line.strip() for line in source.splitlines() if line.strip()), "")
    if first.startswith("# fragment"):
        assert data, f"{where}: an empty fragment"
        return
    import torchdeform as td

    path = work_folder(tmp_path) / "scene.toml"
    path.write_text(source, encoding="utf-8")
    scene = td.load_scene(path)
    assert scene.grid.num_nodes > 0, where


def test_pages_tell_no_history():
    found = [
        f"{page.relative_to(ROOT).as_posix()}:{text.count(chr(10), 0, m.start()) + 1}: {m.group(0)!r}"
        for page in pages()
        for text in [page.read_text(encoding="utf-8")]
        for m in HISTORY.finditer(text)
    ]
    assert not found, f"pages that tell the development history: {found}"


def test_readme_links_exist():
    text = README.read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [t for t in targets if "://" not in t]
    assert local, "README.md links nothing in the repository"
    absent = sorted(t for t in local if not (ROOT / t).exists())
    assert not absent, f"README.md links {absent}, which do not exist"


# ------------------------------------------------------------------ the layout
def section(path: Path, title: str) -> str:
    text = path.read_text(encoding="utf-8")
    m = re.search(rf"^#+ {re.escape(title)}[ \t]*\n(.*?)(?=^#+ |\Z)", text, re.M | re.S)
    assert m, f"{path.relative_to(ROOT)} has no '{title}' section"
    return m.group(1)


def subpackages() -> list[str]:
    return sorted(d.name for d in PACKAGE.iterdir() if (d / "__init__.py").is_file())


def test_readme_names_every_subpackage():
    where = section(README, "Where things are")
    missing = [name for name in subpackages() if f"torchdeform/{name}/" not in where]
    assert not missing, f"'Where things are' in README.md does not list torchdeform/{{{', '.join(missing)}}}/"


def test_readme_names_only_what_exists():
    where = section(README, "Where things are")
    named = set(re.findall(r"torchdeform/([A-Za-z_]\w*(?:/|\.py))", where))
    absent = sorted(n for n in named if not (PACKAGE / n.rstrip("/")).exists())
    assert not absent, f"'Where things are' in README.md names torchdeform/{absent} that do not exist"
    folders = set(re.findall(r"^- `([a-z]\w*)/`", where, re.M))
    absent = sorted(f for f in folders if not (ROOT / f).is_dir())
    assert not absent, f"'Where things are' in README.md names top-level folders {absent} that do not exist"


def layout_bullets() -> dict[str, str]:
    text = section(LAYOUT, "The library, `torchdeform/`")
    return {m.group(1): m.group(2) for m in re.finditer(r"^- `torchdeform/(\w+)/`(.*?)(?=^- |\Z)", text, re.M | re.S)}


def test_layout_lists_every_subpackage():
    bullets = layout_bullets()
    missing = [name for name in subpackages() if name not in bullets]
    assert not missing, f"docs/layout.md does not list torchdeform/{{{', '.join(missing)}}}/"


def test_layout_names_every_module():
    missing = {}
    for name, bullet in layout_bullets().items():
        folder = PACKAGE / name
        modules = [f.stem for f in folder.glob("*.py") if not f.stem.startswith("__")]
        modules += [d.name for d in folder.iterdir() if (d / "__init__.py").is_file()]
        absent = sorted(m for m in modules if f"`{m}`" not in bullet)
        if absent:
            missing[name] = absent
    assert not missing, f"docs/layout.md does not name these modules: {missing}"


def test_layout_names_only_what_exists():
    bullets = layout_bullets()
    absent = sorted(name for name in bullets if not (PACKAGE / name).is_dir())
    assert not absent, f"docs/layout.md names torchdeform/{absent}/ that do not exist"
    text = LAYOUT.read_text(encoding="utf-8")
    named = set(re.findall(r"torchdeform/([A-Za-z_]\w*(?:/|\.py))", text))
    absent = sorted(n for n in named if not (PACKAGE / n.rstrip("/")).exists())
    assert not absent, f"docs/layout.md names torchdeform/{absent} that do not exist"


def test_readme_test_command_is_what_ci_runs():
    """``.ci/run`` calls exactly the README's second command (the full suite), and the README says so."""
    command = (ROOT / ".ci" / "run").read_text(encoding="utf-8").strip().splitlines()[-1]
    assert "--runslow" in command and "mkdocs build --strict" in command, command
    blocks = re.findall(r"^```bash\n(.*?)^```", README.read_text(encoding="utf-8"), re.M | re.S)
    assert any(b.strip() == command for b in blocks), f"no ```bash block of the README is .ci/run's {command!r}"

"""Package layout: the import graph of torchdeform, read from the source with ``ast``.

* the module import graph (every ``import`` statement, also those inside functions, but not those
  under ``if TYPE_CHECKING:``, which only annotations use) is acyclic;
* imports run down the floors of the package (``LAYERS``), never up, and only ``cli`` imports ``bench``;
* no module imports a ``_private`` name (or a ``_private`` module) from another subpackage
  (subpackage = the first component below ``torchdeform``; each top-level module is its own;
  ``torchdeform._compile`` is the shared ground floor, importable everywhere, though the
  underscore names inside it are still private);
* ``import torchdeform`` and building the CLI parser load none of the heavy optional libraries.

Imports by computed name (``importlib.import_module`` in the bench registry) are not seen here.
"""

from __future__ import annotations

import ast
import functools
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "torchdeform"
GROUND_FLOOR = "torchdeform._compile"
HEAVY = ("matplotlib", "trimesh", "scipy", "warp", "nibabel", "nrrd", "skfuzzy", "pydicom", "skimage")


# ------------------------------------------------------------------ the graph
def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PKG.rglob("*.py")) if "__pycache__" not in p.parts}


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _resolve(importer: str, level: int, module: str | None) -> str:
    """The absolute module of ``from <level dots><module> import ...`` written in ``importer``."""
    if level == 0:
        return module or ""
    package = importer.split(".") if _is_package(importer) else importer.split(".")[:-1]
    if level - 1 >= len(package):
        raise AssertionError(f"{importer}: relative import beyond the top-level package")
    base = package[: len(package) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def _ours(name: str) -> bool:
    return name == "torchdeform" or name.startswith("torchdeform.")


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def imports_of(name: str):
    """``(target module, imported name or None, line)`` for every torchdeform import in ``name``.

    ``from .x import y`` gives ``(x.y, None)`` when ``y`` is a submodule, else ``(x, "y")``."""
    tree = ast.parse(MODULES[name].read_text(), filename=str(MODULES[name]))
    typing_only = {
        id(inner)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and _is_type_checking(block.test)
        for stmt in block.body
        for inner in ast.walk(stmt)
    }
    for node in ast.walk(tree):
        if id(node) in typing_only:  # ``if TYPE_CHECKING:`` imports are for annotations, never run
            continue
        if isinstance(node, ast.Import):
            for alias in node.names:
                if _ours(alias.name):
                    yield alias.name, None, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(name, node.level, node.module)
            if not _ours(base):
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if sub in MODULES:
                    yield sub, None, node.lineno
                else:
                    yield base, alias.name, node.lineno


@functools.cache
def import_table() -> dict:
    """Every module's torchdeform imports (parsed once, when a test first needs them)."""
    return {name: list(imports_of(name)) for name in MODULES}


@functools.cache
def import_graph() -> dict:
    """Module -> the torchdeform modules it imports."""
    return {name: sorted({target for target, _, _ in found}) for name, found in import_table().items()}


def find_cycle(graph: dict) -> list | None:
    """One cycle ``[a, b, ..., a]`` of a directed graph ``{node: [successors]}``, or ``None``."""
    colour = dict.fromkeys(graph, 0)  # 0 unseen, 1 on the current path, 2 done
    path = []

    def visit(node):
        colour[node] = 1
        path.append(node)
        for nxt in graph.get(node, ()):
            if colour.get(nxt, 0) == 1:
                return path[path.index(nxt) :] + [nxt]
            if colour.get(nxt, 0) == 0:
                found = visit(nxt)
                if found:
                    return found
        colour[node] = 2
        path.pop()
        return None

    for start in sorted(graph):
        if colour[start] == 0:
            found = visit(start)
            if found:
                return found
    return None


def group(module: str) -> str:
    """The subpackage of a module (``sim``, ``learn``, ...), or the top-level module itself."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_imports() -> list:
    """Every import of a private name or private module across subpackages, as readable lines."""
    bad = []
    for importer, found in import_table().items():
        for target, name, line in found:
            if group(importer) == group(target):
                continue
            where = f"{MODULES[importer].relative_to(ROOT)}:{line}"
            if target != GROUND_FLOOR and any(_private(p) for p in target.split(".")[1:]):
                bad.append(f"{where}: {importer} imports the private module {target}")
            if name is not None and _private(name):
                bad.append(f"{where}: {importer} imports the private name {target}.{name}")
    return bad


# ------------------------------------------------------------------ tests
def test_graph_sees_the_package():
    assert {"torchdeform", "torchdeform.sim", "torchdeform.sim.springs", "torchdeform.cli", GROUND_FLOOR} <= set(
        MODULES
    )
    assert "torchdeform.sim" in import_graph()["torchdeform"]
    unknown = [(m, t) for m, found in import_table().items() for t, _, _ in found if t not in MODULES]
    assert not unknown, f"imports that resolve to no module of the package: {unknown}"


def test_relative_import_resolution():
    assert _resolve("torchdeform.sim.model", 1, "springs") == "torchdeform.sim.springs"
    assert _resolve("torchdeform.sim.model", 2, "errors") == "torchdeform.errors"
    assert _resolve("torchdeform.sim", 1, "grid") == "torchdeform.sim.grid"
    assert _resolve("torchdeform.sim", 2, None) == "torchdeform"
    assert _resolve("torchdeform.cli", 1, None) == "torchdeform"


def test_cycle_finder_finds_cycles():
    assert find_cycle({"a": ["b"], "b": ["c"], "c": []}) is None
    assert find_cycle({"a": ["b"], "b": ["c"], "c": ["a"]}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": ["a"]}) == ["a", "a"]


def test_import_graph_is_acyclic():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_private_imports_across_subpackages():
    assert group("torchdeform.sim.springs") == "sim" and group("torchdeform.mesh") == "mesh"
    bad = private_imports()
    assert not bad, "private imports across subpackages:\n" + "\n".join(bad)


def _loaded_heavy(statement: str) -> list:
    code = (
        f"import json, sys\n{statement}\n"
        f"print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r})))"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


def _loaded_compiler(statement: str) -> list:
    """The torch compiler modules (dynamo, inductor: ~1.7 s to import) loaded by ``statement``."""
    code = (
        f"import json, sys\n{statement}\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.startswith(('torch._inductor', 'torch._dynamo', '"
        "torchdeform._compile')))))"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize(
    "statement", ["import torchdeform", "from torchdeform.cli import build_parser; build_parser()"]
)
def test_heavy_libraries_are_not_loaded(statement):
    assert _loaded_heavy(statement) == []
    assert _loaded_compiler(statement) == []  # every command's start-up would pay for it


def test_eager_native_steps_do_not_load_the_compiler():
    """The C kernels' eager calls skip their custom ops (whose first call imports torch._dynamo, 1.2 s):
    a native run of an Elastic body (springs and cell term by C) loads no compiler module."""
    from torchdeform.sim import native

    if native.unavailable():
        pytest.skip(native.unavailable())
    run = (
        "import torch, torchdeform as td\n"
        "g = td.Grid((4, 4, 4), spacing=0.01, topology=26)\n"
        "drag = td.Drag(g.face('top'), offset=(0.001, 0.0, 0.0), period=0.1)\n"  # not the fused step
        "m = td.Model(g, stiffness=td.Elastic(5e3, 0.45), density=1000.0, fixed=g.face('bottom'), drags=[drag])\n"
        "e = td.Engine(mode='native')\n"
        "td.simulate(m, m.rest_state(), 1e-4, 5, engine=e, warn=False)\n"
        "assert e.ran == 'native' and e.step.fused is None and e.step.packed.volume_kernel, e.reason"
    )
    torch_compiler = [m for m in _loaded_compiler(run) if m.startswith("torch.")]
    assert torch_compiler == []
    assert "torch._dynamo" in _loaded_compiler(run + "\nimport torch._dynamo")  # the check sees it loaded


def test_heavy_library_check_can_fail():
    assert "scipy" in _loaded_heavy("import scipy")


# ------------------------------------------------------------------ layers
#: the floors of the package, bottom to top (``../DESIGN.md``); an import runs down or sideways, never up
LAYERS = [
    {"errors", "options", "outputs", "checks", "cpu_load", "_compile"},  # the ground floor
    {"sim"},
    {"fuzzy", "volume", "chainmail", "mesh"},
    {"interact", "topology", "learn", "anatomy", "texture"},
    {"scene"},
    {"view", "distributed"},
    {"torchdeform"},  # the package's own face (``import torchdeform as td``)
    {"bench"},
    {"cli"},
    {"__main__"},  # ``python -m torchdeform``
]
FLOOR = {group: n for n, floor in enumerate(LAYERS) for group in floor}


def upward_imports(imports=None) -> list:
    """Every import from a lower floor to a higher one, and every import of ``bench`` outside ``cli``."""
    bad = []
    for importer, found in (import_table() if imports is None else imports).items():
        for target, _, line in found:
            a, b = group(importer), group(target)
            where = f"{MODULES[importer].relative_to(ROOT) if importer in MODULES else importer}:{line}"
            if FLOOR[b] > FLOOR[a]:
                bad.append(f"{where}: {importer} ({a}, floor {FLOOR[a]}) imports {target} ({b}, floor {FLOOR[b]})")
            elif b == "bench" and a not in ("bench", "cli"):
                bad.append(f"{where}: {importer} imports {target}: only cli imports bench")
    return bad


def test_every_subpackage_has_a_floor():
    groups = {group(m) for m in MODULES}
    assert groups <= set(FLOOR), f"subpackages without a floor in LAYERS: {sorted(groups - set(FLOOR))}"


def test_layer_check_can_fail():
    fake = {"torchdeform.sim.model": [("torchdeform.scene.run", None, 3), ("torchdeform.bench.common", None, 4)]}
    bad = upward_imports(fake)
    assert len(bad) == 2 and "floor 1" in bad[0] and "floor 4" in bad[0]


def test_imports_run_down_the_layers():
    bad = upward_imports()
    assert not bad, "imports that run up the layers:\n" + "\n".join(bad)

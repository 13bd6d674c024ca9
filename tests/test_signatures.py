"""Optional arguments are keyword-only across the public API.

Every function, class and public method that a module lists in ``__all__`` takes its optional
arguments (those with a default) by keyword only: ``render(volume, mode="mip", size=64)``, never
``render(volume, "mip", 64)``. A call that passes them by position fails with Python's own
``TypeError`` ("takes 1 positional argument but 3 were given").

Oracle: :func:`inspect.signature` of the objects themselves, walked from every module's ``__all__``.
Named tuples are left out (their fields are positional by nature).
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

import torchdeform

SUBPACKAGES = sorted(
    {m.name.split(".")[1] for m in pkgutil.iter_modules(torchdeform.__path__, "torchdeform.") if m.ispkg}
    | {"torchdeform"}
)


def _modules(group: str):
    """The modules of one subpackage (``sim``, ...) or, for ``torchdeform``, the top-level modules."""
    if group == "torchdeform":
        names = ["torchdeform"] + [
            m.name for m in pkgutil.iter_modules(torchdeform.__path__, "torchdeform.") if not m.ispkg
        ]
    else:
        pkg = importlib.import_module(f"torchdeform.{group}")
        names = [pkg.__name__] + [m.name for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")]
    return [importlib.import_module(n) for n in names if not n.endswith("__main__")]


def _positional_defaults(fn) -> list[str]:
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return []
    return [p.name for p in sig.parameters.values() if p.kind is p.POSITIONAL_OR_KEYWORD and p.default is not p.empty]


def violations(group: str) -> list[str]:
    """``module.name(args)`` for every public callable of ``group`` with an optional positional argument."""
    bad = []
    for mod in _modules(group):
        for name in getattr(mod, "__all__", ()):
            obj = getattr(mod, name, None)
            if obj is None or getattr(obj, "__module__", None) != mod.__name__:
                continue  # judged where it is defined
            if inspect.isfunction(obj):
                found = [(name, obj)]
            elif inspect.isclass(obj) and not issubclass(obj, tuple):
                found = [(name, obj)]
                for attr, value in vars(obj).items():
                    if attr.startswith("_"):
                        continue
                    fn = value.__func__ if isinstance(value, classmethod | staticmethod) else value
                    if inspect.isfunction(fn):
                        found.append((f"{name}.{attr}", fn))
            else:
                continue
            for qual, fn in found:
                names = _positional_defaults(fn)
                if names:
                    bad.append(f"{mod.__name__}.{qual}({', '.join(names)})")
    return bad


def test_scan_finds_a_positional_default():
    def f(a, b=1, *, c=2):
        return a + b + c

    def g(a, *, b=1):
        return a + b

    assert _positional_defaults(f) == ["b"] and _positional_defaults(g) == []


@pytest.mark.parametrize("group", SUBPACKAGES)
def test_optional_arguments_are_keyword_only(group):
    bad = violations(group)
    assert not bad, f"{len(bad)} public callables take optional arguments by position:\n" + "\n".join(bad)

"""The root API: every public name of ``import torchdeform as td`` shows a runnable example.

The examples themselves run as doctests (``--doctest-modules`` in the test command); this test
checks that none is missing: a function, class or subpackage needs ``>>>`` lines in its own
docstring, a constant (``INTEGRATORS``) in the docstring of the module that defines it.
"""

from __future__ import annotations

import inspect
import sys

import pytest

import torchdeform as td


def _docstring(name: str) -> str:
    obj = getattr(td, name)
    if inspect.ismodule(obj) or inspect.isclass(obj) or inspect.isroutine(obj):
        return inspect.getdoc(obj) or ""
    owners = [
        m
        for m in list(sys.modules.values())
        if getattr(m, "__name__", "").startswith("torchdeform.")
        and getattr(m, name, None) is obj
        and name in getattr(m, "__all__", ())
    ]
    owner = max(owners, key=lambda m: m.__name__.count("."))  # the defining module, not a re-export
    return owner.__doc__ or ""


@pytest.mark.parametrize("name", sorted(td.__all__))
def test_root_name_has_an_example(name):
    assert ">>>" in _docstring(name), f"td.{name} has no Examples block in its docstring"


def test_all_names_exist():
    assert not [n for n in td.__all__ if not hasattr(td, n)]

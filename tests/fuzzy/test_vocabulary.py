"""The vocabulary table: complete against the engine, the same in the guide, and drawn.

Oracles: the engine's own registries (membership kinds, hedges, norms, defuzzifiers), the
guide's text, and the PNG's header and size.
"""

from __future__ import annotations

from pathlib import Path

from torchdeform import cli
from torchdeform.fuzzy.membership import HEDGES, KINDS
from torchdeform.fuzzy.system import AGGREGATIONS, AND_METHODS, DEFUZZIFIERS, IMPLICATIONS, OR_METHODS
from torchdeform.fuzzy.vocabulary import EXAMPLE_PARAMETERS, VOCABULARY, plot_kinds, vocabulary_table

GUIDE = Path(__file__).resolve().parents[2] / "docs" / "guide" / "fuzzy.md"


def _ours(kind_prefix: str) -> set:
    return {row[1] for row in VOCABULARY if row[0].startswith(kind_prefix)}


def test_every_word_of_the_engine_has_a_row():
    assert _ours("membership") == set(KINDS) == set(EXAMPLE_PARAMETERS)
    assert {w for row in VOCABULARY if row[0] == "hedge" for w in row[1].split()} == set(HEDGES)
    assert _ours("AND") == set(AND_METHODS) == set(IMPLICATIONS)
    assert _ours("OR") | _ours("aggregation") == set(OR_METHODS) | set(AGGREGATIONS)
    assert _ours("defuzzification") == set(DEFUZZIFIERS)
    assert all(len(row) == 6 and all(row) for row in VOCABULARY)


def test_the_guide_holds_the_same_table():
    assert vocabulary_table() in GUIDE.read_text()


def test_the_command_prints_the_table_and_draws_every_kind(tmp_path, capsys):
    assert cli.main(argv=["fuzzy", "vocabulary", "--out", str(tmp_path / "kinds")]) == 0
    out = capsys.readouterr().out
    assert out.strip() == vocabulary_table()
    png = (tmp_path / "kinds" / "membership_kinds.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


def test_plot_kinds_returns_its_path(tmp_path):
    assert plot_kinds(tmp_path / "k.png") == tmp_path / "k.png"

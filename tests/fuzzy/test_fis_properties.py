"""Property tests (hypothesis): ``.fis`` write then read gives the same system, on random systems.

The systems come from the oracle's descriptions (:func:`tests.oracles.fuzzy.random_system`, built
by :func:`tests.oracles.fuzzy.build_torch` from the rule sentences) with random inference methods,
resolutions and hedges. What is read back is checked against the description (names, ranges,
term kinds and parameters, defaults, rule clauses, connectives and weights) and must give
bit-identical outputs to the system that was written, in either dialect of rule codes. Systems
with hedge combinations that the dialect cannot encode (Octave's: anything but an optional
leading NOT followed by somewhat, very, cubed or very very, on inputs and outputs; fuzzylite's:
an optional NOT followed by seldom, somewhat, very, extremely, very very or any, on inputs only)
must be refused with a :class:`ConfigError`.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.oracles.fuzzy import build_torch, default_dtype, random_points, random_system
from torchdeform.errors import ConfigError
from torchdeform.fuzzy.fis import fis_text, parse_fis, read_fis, write_fis

#: What a .fis rule can say about a clause after an optional leading NOT, per dialect of codes.
ENCODABLE = {
    "octave": {(), ("somewhat",), ("very",), ("cubed",), ("very", "very")},
    "fuzzylite": {(), ("seldom",), ("somewhat",), ("very",), ("extremely",), ("very", "very"), ("any",)},
}

METHODS = st.fixed_dictionaries(
    {
        "and_method": st.sampled_from(["min", "prod"]),
        "or_method": st.sampled_from(["max", "probor"]),
        "implication": st.sampled_from(["min", "prod"]),
        "aggregation": st.sampled_from(["max", "sum", "probor"]),
        "defuzzification": st.sampled_from(["centroid", "bisector", "mom", "som", "lom"]),
    }
)


def _encodable(spec, dialect: str) -> bool:
    for rule in spec.rules:
        if dialect == "fuzzylite" and any(c.hedges for c in rule.cons):
            return False  # fuzzylite hedges a consequent's activation, not its term: refused
        for clause in rule.ante + rule.cons:
            h = tuple(clause.hedges)
            if (h[1:] if h[:1] == ("not",) else h) not in ENCODABLE[dialect]:
                return False
    return True


def in_input_order(spec):
    """The same system with each rule's clauses in the order of the inputs.

    A .fis rule line lists one code per input, so it cannot keep the order of the clauses of a
    sentence; with ``prod``/``probor`` over three or more clauses a different order rounds
    differently (a few ulp; ``mom``/``som``/``lom`` can turn that into a jump). Identical outputs
    are only promised for systems whose clauses already come in input order.
    """
    order = {v.name: i for i, v in enumerate(spec.inputs)}
    for rule in spec.rules:
        rule.ante.sort(key=lambda c: order[c.var])
    return spec


def _as(dtype, value: float) -> float:
    return float(np.float32(value)) if dtype == torch.float32 else float(value)


def _check_against_spec(back, spec, dtype):
    assert back.name == spec.name
    for variables, specs in ((back.inputs, spec.inputs), (back.outputs, spec.outputs)):
        assert [v.name for v in variables] == [v.name for v in specs]
        for var, vs in zip(variables, specs):
            assert var.range == (vs.lo, vs.hi)
            assert var.term_names == [t.name for t in vs.terms]
            for t in vs.terms:
                mf = var.terms[t.name]
                assert mf.kind == t.kind
                assert mf.values() == [_as(dtype, p) for p in t.params], (var.name, t.describe())
    for var, vs in zip(back.outputs, spec.outputs):
        assert var.default == vs.fallback
    assert len(back.rules) == len(spec.rules)
    for rule, rs in zip(back.rules, spec.rules):
        # "any" (fuzzylite's 0.99) names no term: it reads back on the first, to the same degree 1
        assert {
            (c.variable, c.term if c.hedges[-1:] != ("any",) else "", tuple(c.hedges)) for c in rule.antecedent
        } == {(c.var, c.term if c.hedges[-1:] != ("any",) else "", tuple(c.hedges)) for c in rs.ante}
        assert {(c.variable, c.term) for c in rule.consequent} == {(c.var, c.term) for c in rs.cons}
        assert rule.weight == rs.weight
        assert len(rs.ante) == 1 or rule.connective == rs.connective  # one clause: no connective


HEDGES = {d: sorted(e) + [("not",) + h for h in sorted(e)] for d, e in ENCODABLE.items()}
UNENCODABLE = [("somewhat", "very"), ("very", "not"), ("not", "not"), ("extremely", "seldom"), ("any", "very")]


@settings(max_examples=150, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    hedges=st.sampled_from(["oracle", "encodable", "any"]),
    dialect=st.sampled_from(["octave", "fuzzylite"]),
    methods=METHODS,
    resolution=st.sampled_from([300, 1000, 3000]),
    dtype=st.sampled_from([torch.float32, torch.float64]),
    data=st.data(),
)
def test_fis_round_trip_gives_identical_outputs(seed, hedges, dialect, methods, resolution, dtype, data):
    """``hedges``: the oracle's own choice (a few NOTs), or hedges drawn here for every clause
    (outputs included) from the encodable set, or from it and some combinations that are not."""
    spec = in_input_order(random_system(seed, methods=methods))
    if hedges != "oracle":
        choice = st.sampled_from(HEDGES[dialect] + (UNENCODABLE if hedges == "any" else []))
        for rule in spec.rules:
            for clause in rule.ante + rule.cons:
                clause.hedges = data.draw(choice)
    system = build_torch(spec, dtype=dtype, resolution=resolution)
    if not _encodable(spec, dialect):
        with pytest.raises(ConfigError, match="hedge"):
            fis_text(system, hedges=dialect)
        return
    text = fis_text(system, comments=f"seed {seed}", hedges=dialect)
    with default_dtype(dtype):  # read the parameters in the system's dtype
        back = parse_fis(text, path=f"random{seed}.fis", hedges=dialect)
    _check_against_spec(back, spec, dtype)
    assert back.resolution == resolution
    assert (back.and_method, back.or_method, back.implication, back.aggregation, back.defuzzification) == tuple(
        methods[k] for k in ("and_method", "or_method", "implication", "aggregation", "defuzzification")
    )
    assert fis_text(back, comments=f"seed {seed}", hedges=dialect) == text
    x = torch.tensor(random_points(spec, seed, 64), dtype=dtype)
    assert torch.equal(back(x), system(x))


def test_fis_file_round_trip(tmp_path):
    """The same through a file on disk (write_fis / read_fis) for one random system."""
    spec = in_input_order(random_system(7))
    system = build_torch(spec)
    with default_dtype(torch.float64):
        back = read_fis(write_fis(system, tmp_path / "s.fis"))
    _check_against_spec(back, spec, torch.float64)
    x = torch.tensor(random_points(spec, 7, 64), dtype=torch.float64)
    assert torch.equal(back(x), system(x))

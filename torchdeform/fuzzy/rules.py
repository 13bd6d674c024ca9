"""Linguistic variables and rules, readable as sentences.

A rule reads like the sentence a surgeon would say::

    IF consistency IS very soft AND sensitiveness IS NOT large THEN spring_const IS small
    AND viscosity IS large WITH 0.5

``IS`` may be followed by hedges (``very``, ``somewhat``, ``extremely``, ``seldom``, ``any``,
``cubed``, ``not``; several in a row, read left to right: "not very soft" = not(very(soft))),
in conditions and conclusions alike (a hedged conclusion implies the hedged set, as in Octave
and fuzzylite), ``AND`` / ``OR`` join the antecedent clauses (one connective per rule, as in
MATLAB), ``AND`` joins the consequents, and ``WITH w`` (optional) is the rule weight in
``[0, 1]``. Keywords and hedges are case-insensitive; variable and term names are not.

The hedges are fuzzylite's (``extremely`` is its contrast intensifier) plus ``cubed`` (``m^3``).
Octave's fuzzy-logic-toolkit writes a hedge as the fraction of a rule's membership-function
index and raises the degree to a power, NOT (a minus sign) applied after it; in these words:

=============  ===========================  =================================
Octave code    Octave's name and degree     hedges here
=============  ===========================  =================================
``k.05``       somewhat, ``m^0.5``          ``somewhat``
``k.2``        very, ``m^2``                ``very``
``k.3``        extremely, ``m^3``           ``cubed`` (not ``extremely``)
``k.4``        very very, ``m^4``           ``very very``
``-k``         not, ``1 - m``               ``not``
``-k.2``       ``1 - m^2``                  ``not very``
=============  ===========================  =================================

(see :data:`~torchdeform.fuzzy.membership.HEDGES`).
"""

from __future__ import annotations

import math
import re
from dataclasses import KW_ONLY, dataclass, field

import torch
from torch import nn

from ..errors import ConfigError
from .membership import HEDGES, MembershipFunction

__all__ = ["check_name", "Variable", "Clause", "Rule"]

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")


def check_name(name: str, key: str) -> str:
    """A variable or term name: letters, digits, ``_ . -``, not starting with a digit."""
    if not isinstance(name, str) or not _NAME.match(name) or name.upper() in _KEYWORDS or name in HEDGES:
        raise ConfigError(key, "a name of letters, digits and _ . - (not a keyword or hedge)", got=name)
    return name


#: the largest magnitude of a range end or a membership parameter: float32 holds up to 3.4e38, and
#: the centroid sums membership times value over the output cells (resolution 1000 by default)
LIMIT = 1e30
RANGE_TEXT = "two numbers lo < hi of magnitude <= 1e30 (float32 sums over the output cells stay finite)"


class Variable(nn.Module):
    """A linguistic variable: a name, a range and named terms (membership functions).

    Args:
        name: the variable's name (``consistency``).
        range: ``(lo, hi)`` with ``lo < hi``. Inputs are clipped to it before fuzzification
            (as in MATLAB and scikit-fuzzy, whose universes end there); outputs are
            defuzzified over it.
        terms: ``{term name: MembershipFunction}``, in order (the order is the MF index in
            ``.fis`` files).
        default: outputs only: the crisp value when no rule fires for an input row. ``None``
            gives the middle of the range (MATLAB's convention).
    """

    def __init__(self, name: str, range, terms: dict, *, default: float | None = None):
        super().__init__()
        self.name = check_name(name, "variable name")
        try:
            lo, hi = (float(v) for v in range)
        except (TypeError, ValueError):
            raise ConfigError(f"{name}.range", "two numbers lo < hi", got=range) from None
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"{name}.range", "two finite numbers lo < hi", got=(lo, hi))
        if max(abs(lo), abs(hi)) > LIMIT:
            raise ConfigError(f"{name}.range", RANGE_TEXT, got=(lo, hi))
        self.range = (lo, hi)
        # the range as a buffer follows .to()/.double() like the parameters, so a system built in
        # float32 clips inputs to the same rounded ends as its float32 corner points
        self.register_buffer("bounds", torch.tensor([lo, hi], dtype=torch.get_default_dtype()))
        if not terms:
            raise ConfigError(f"{name}.terms", "at least one term", got=terms)
        for t, mf in terms.items():
            check_name(t, f"{name} term name")
            if not isinstance(mf, MembershipFunction):
                raise ConfigError(f"{name}.{t}", "a membership function", got=mf)
        self.terms = nn.ModuleDict(terms)
        self.default = 0.5 * (lo + hi) if default is None else float(default)

    @property
    def term_names(self) -> list:
        """The term names, in order (the term index of a ``.fis`` file is its position here plus one)."""
        return list(self.terms.keys())

    def index(self, term: str, *, key: str = "term") -> int:
        """The position of ``term`` in :attr:`term_names`; :class:`ConfigError` under ``key`` if there is none."""
        try:
            return self.term_names.index(term)
        except ValueError:
            raise ConfigError(key, f"a term of {self.name} ({', '.join(self.term_names)})", got=term) from None

    def __repr__(self) -> str:
        terms = ", ".join(f"{t}={mf!r}" for t, mf in self.terms.items())
        return f"Variable({self.name!r}, range={self.range}, {terms})"


@dataclass(frozen=True)
class Clause:
    """``variable IS [hedges] term``; ``hedges`` outermost first, e.g. ``("not", "very")``."""

    variable: str
    term: str
    _: KW_ONLY
    hedges: tuple = ()

    def __str__(self) -> str:
        return " ".join([self.variable, "IS", *self.hedges, self.term])


@dataclass
class Rule:
    """One Mamdani rule.

    Attributes:
        antecedent: clauses joined by ``connective`` (``"and"`` or ``"or"``).
        consequent: output clauses (each output at most once).
        weight: in ``[0, 1]``; multiplies the firing degree.
    """

    antecedent: list
    consequent: list
    _: KW_ONLY
    connective: str = "and"
    weight: float = 1.0
    text: str = field(default="", compare=False)

    def __post_init__(self):
        if self.connective not in ("and", "or"):
            raise ConfigError("rule connective", "'and' or 'or'", got=self.connective)
        if not self.antecedent:
            raise ConfigError("rule", "at least one antecedent clause", got=str(self))
        if not self.consequent:
            raise ConfigError("rule", "at least one consequent clause", got=str(self))
        w = float(self.weight)
        if not (0.0 <= w <= 1.0):
            raise ConfigError("rule weight", "a number in [0, 1]", got=self.weight)
        self.weight = w
        outs = [c.variable for c in self.consequent]
        if len(set(outs)) != len(outs):
            raise ConfigError("rule", "each output at most once in a consequent", got=str(self))

    def __str__(self) -> str:
        join = f" {self.connective.upper()} "
        s = "IF " + join.join(map(str, self.antecedent)) + " THEN " + " AND ".join(map(str, self.consequent))
        return s + (f" WITH {self.weight!r}" if self.weight != 1.0 else "")

    @staticmethod
    def parse(text: str) -> Rule:
        """Parse a rule sentence (see the module docstring).

        Raises :class:`ConfigError` naming the rule and what was expected.
        """
        return _parse(text)


_KEYWORDS = {"IF", "THEN", "IS", "AND", "OR", "WITH"}


def _parse(text: str) -> Rule:
    words = str(text).replace("(", " ").replace(")", " ").split()

    def fail(expected, got):
        raise ConfigError(f"rule {text.strip()!r}", expected, got=got)

    if not words or words[0].upper() != "IF":
        fail("a sentence starting with IF", words[0] if words else "")
    up = [w.upper() for w in words]
    if "THEN" not in up:
        fail("THEN between the conditions and the conclusions", None)
    then = up.index("THEN")
    weight = 1.0
    end = len(words)
    if "WITH" in up:
        k = up.index("WITH")
        if k < then or k != len(words) - 2:
            fail("WITH <weight> at the end", " ".join(words[k:]))
        try:
            weight = float(words[k + 1])
        except ValueError:
            fail("a number after WITH", words[k + 1])
        end = k

    def clauses(ws, allow_or):
        out, conns, cur = [], set(), []
        for _i, w in enumerate(ws + [None]):
            if w is not None and w.upper() not in ("AND", "OR"):
                cur.append(w)
                continue
            if w is not None:
                if w.upper() == "OR" and not allow_or:
                    fail("AND between conclusions", "OR")
                conns.add(w.lower())
            if len(cur) < 3 or cur[1].upper() != "IS":
                fail("'variable IS [hedge ...] term'", " ".join(cur))
            if cur[-1] in HEDGES:
                fail("a term after the hedges", " ".join(cur))
            hedges = tuple(h.lower() for h in cur[2:-1])
            for h in hedges:
                if h not in HEDGES:
                    fail(f"a hedge ({', '.join(HEDGES)}) before the term", h)
            out.append(Clause(cur[0], cur[-1], hedges=hedges))
            cur = []
        return out, conns

    ante, conns = clauses(words[1:then], True)
    if len(conns) > 1:
        fail("one connective per rule (all AND or all OR)", "AND and OR mixed")
    cons, _ = clauses(words[then + 1 : end], False)
    connective = "or" if "or" in conns else "and"
    try:
        return Rule(ante, cons, connective=connective, weight=weight, text=str(text).strip())
    except ConfigError as e:  # weight out of [0, 1], an output twice: name the rule
        fail(e.expected, e.got)

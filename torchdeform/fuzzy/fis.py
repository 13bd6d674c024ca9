"""MATLAB ``.fis`` files: read and write Mamdani systems (MATLAB's, Octave's and fuzzylite's).

The format (Fuzzy Logic Toolbox), as read here::

    % comment lines start with % or #; a % or # outside quotes ends a line's value
    [System]
    Name='tissue'
    Type='mamdani'
    NumInputs=1
    NumOutputs=2
    NumRules=7
    AndMethod='min'          min | prod | the other t-norms of AND_METHODS (Octave's, fuzzylite's)
    OrMethod='max'           max | probor | the other s-norms of OR_METHODS
    ImpMethod='min'          a t-norm of IMPLICATIONS
    AggMethod='max'          an s-norm of AGGREGATIONS
    DefuzzMethod='centroid'  centroid | bisector | mom | som | lom (Octave's centroid_integral = centroid)

    [Input1]
    Name='consistency'
    Range=[0 12]
    NumMFs=7
    MF1='flexible':'trapmf',[0 0 1.5 3]

    [Output1]
    Name='spring_const'
    Range=[0 100]
    NumMFs=5
    MF1='very_small':'trimf',[0 0 10]

    [Rules]
    1, 2 2 (1) : 1

A rule line lists one membership-function index per input, a comma, one per output, the
weight in parentheses and ``: 1`` (AND) or ``: 2`` (OR). Index 0 means "not used"; a negative
index means NOT; the fractional part encodes a hedge, in one of two dialects (the ``hedges``
keyword of every function here):

=========  ===============================  ========================================
code       ``hedges="octave"`` (default)    ``hedges="fuzzylite"``
=========  ===============================  ========================================
``.01``    (mu^0.1: refused)                seldom
``.05``    somewhat (mu^0.5)                somewhat
``.1``     none (mu^1)                      (refused)
``.2``     very (mu^2)                      very
``.3``     cubed (mu^3)                     extremely (fuzzylite's contrast hedge)
``.4``     very very (mu^4)                 very very
``.99``    (mu^9.9: refused)                any (``0.99``: no term)
=========  ===============================  ========================================

Octave's fuzzy-logic-toolkit raises a degree to the power ``dd/10`` for a fraction ``.dd``
(``get_mf_index_and_hedge.m``, ``evalmf.m``), NOT last (``-2.3`` = not(cubed(term))), on
inputs and outputs alike; powers other than those above are refused. fuzzylite
(``FisImporter.cpp``) names its hedges and applies a consequent's hedges to the rule's
activation degree, not to the output term as Octave and this engine do: a hedged or negated
consequent is refused in that dialect. Writing a hedge the dialect cannot encode is refused.

Membership types (parameters in the file's order; see :mod:`~torchdeform.fuzzy.membership`):
MATLAB's ``trapmf trimf gaussmf [sigma c] gbellmf sigmf [a c] zmf smf pimf dsigmf psigmf
gauss2mf [sigma1 c1 sigma2 c2]``, Octave's ``linsmf linzmf``, fuzzylite's ``rampmf rectmf
concavemf cosinemf spikemf binarymf discretemf [x1 y1 x2 y2 ...]`` and our ``singletonmf [v]``.
MATLAB's own functions ignore parameters after the ones they use (old files padded them with
zeros): those are read with a warning; for the other types a wrong count is refused.
``Default=v`` in an output section (ours and fuzzylite's) sets the value used when no rule
fires (MATLAB's mid-range when absent or ``nan``). ``Resolution`` (ours, grid cells per
output) is read in ``[System]``.

Lenient where the peers are: a key this reader does not use (fuzzylite's ``Enabled=1``,
``LockPrevious=0``, ``LockRange``, newer MATLAB keys) is read with one :class:`FisWarning`
naming file, line and key; a key whose value would change the result if ignored
(``Enabled=0``, ``LockPrevious=1``, a ``LockRange=1`` that would clip an output, a type-2
``TypeReductionMethod``) is refused. Sugeno systems are refused.

A malformed file is rejected with a :class:`~torchdeform.errors.ConfigError` whose message
names the file, the line and what was expected, e.g.
``tipper.fis:14: [Input2] MF3: expected 'name':'type',[params], got "'good':trimf [5 10 10]"``.

Example:
    >>> import torch
    >>> from torchdeform.fuzzy.fis import read_fis, write_fis
    >>> from torchdeform.fuzzy.presets import preset_path
    >>> fis = read_fis(preset_path("susilap_g"))                 # the shipped fuzzy/susilap_g.fis
    >>> path = write_fis(fis, getfixture("tmp_path") / "copy.fis")
    >>> x = torch.tensor([[2.5], [5.5], [10.1]])
    >>> torch.equal(read_fis(path)(x), fis(x))
    True
"""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np
import torch

from ..checks import read_text
from ..errors import ConfigError
from .membership import (
    Bell,
    Binary,
    Concave,
    Cosine,
    DiffSigmoid,
    Discrete,
    Gaussian,
    Gaussian2,
    LinS,
    LinZ,
    PiShape,
    ProdSigmoid,
    Ramp,
    Rectangle,
    Sigmoid,
    Singleton,
    Spike,
    SShape,
    Trapezoid,
    Triangle,
    ZShape,
)
from .rules import LIMIT, RANGE_TEXT, Clause, Rule, Variable
from .system import AGGREGATIONS, AND_METHODS, DEFUZZIFIERS, IMPLICATIONS, OR_METHODS, MamdaniSystem

__all__ = ["FisWarning", "DIALECTS", "parse_fis", "read_fis", "fis_text", "write_fis"]


class FisWarning(UserWarning):
    """A ``.fis`` line read leniently (a key this reader does not use, extra MF parameters ...)."""


#: the hedge-code dialects of the ``hedges`` keyword
DIALECTS = ("octave", "fuzzylite")

# file name -> (our class, file order as indices into our order or None for the same order,
# whether extra parameters are ignored with a warning, as MATLAB's own functions do)
_MF_READ = {
    "trapmf": (Trapezoid, (0, 1, 2, 3), True),
    "trimf": (Triangle, (0, 1, 2), True),
    "gaussmf": (Gaussian, (1, 0), True),  # [sigma c] -> (mean, sigma)
    "gbellmf": (Bell, (0, 1, 2), True),
    "sigmf": (Sigmoid, (1, 0), True),  # [a c] = [slope center] -> (center, slope)
    "zmf": (ZShape, None, True),
    "smf": (SShape, None, True),
    "pimf": (PiShape, None, True),
    "dsigmf": (DiffSigmoid, None, True),
    "psigmf": (ProdSigmoid, None, True),
    "gauss2mf": (Gaussian2, None, True),
    "linsmf": (LinS, None, False),
    "linzmf": (LinZ, None, False),
    "rampmf": (Ramp, None, False),
    "rectmf": (Rectangle, None, False),
    "concavemf": (Concave, None, False),
    "cosinemf": (Cosine, None, False),
    "spikemf": (Spike, None, False),
    "binarymf": (Binary, None, False),
    "discretemf": (Discrete, None, False),  # x1 y1 x2 y2 ...: any even count
    "singletonmf": (Singleton, (0,), False),
}
_MF_WRITE = {cls.kind: (name, order) for name, (cls, order, _) in _MF_READ.items()}
_DEFUZZ_ALIASES = {"centroid_integral": "centroid"}  # Octave: the same centroid, by trapz instead of a sum

# fraction * 100 -> hedges (outermost first), per dialect
_HEDGE_CODES = {
    "octave": {0: (), 5: ("somewhat",), 10: (), 20: ("very",), 30: ("cubed",), 40: ("very", "very")},
    "fuzzylite": {
        0: (),
        1: ("seldom",),
        5: ("somewhat",),
        20: ("very",),
        30: ("extremely",),
        40: ("very", "very"),
        99: ("any",),
    },
}
_CODE_OF = {d: {h: c for c, h in codes.items() if h} for d, codes in _HEDGE_CODES.items()}
_CODES_TEXT = {
    "octave": ".05 (somewhat), .2 (very), .3 (cubed, mu^3) or .4 (very very) after the index (Octave's "
    "hedges; other fractions .dd are its custom powers mu^(dd/10), not supported)",
    "fuzzylite": ".01 (seldom), .05 (somewhat), .2 (very), .3 (extremely), .4 (very very) or .99 (any) "
    "after the index (fuzzylite's hedges)",
}
_HEDGE_NAMES = {
    "octave": "not, somewhat, very, cubed, very very",
    "fuzzylite": "not, seldom, somewhat, very, extremely, very very, any",
}

_SYSTEM_KEYS = {
    "Name",
    "Type",
    "Version",
    "NumInputs",
    "NumOutputs",
    "NumRules",
    "AndMethod",
    "OrMethod",
    "ImpMethod",
    "AggMethod",
    "DefuzzMethod",
    "DisableStructuralChecks",
    "Resolution",
}
_VAR_KEYS = {"Name", "Range", "NumMFs"}
_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
# 'name':'type',[params]; group 3 is empty when the type's closing quote is missing, as in
# fuzzylite's exporter's 'binarymf,[...]
_MF_LINE = re.compile(r"^'([^']*)'\s*:\s*'([^',\[\]]*)(')?\s*,\s*\[([^\]]*)\]$")
_NUM_RE = re.compile(_NUM)


def _dialect(hedges) -> str:
    if hedges not in DIALECTS:
        raise ConfigError("hedges", "'octave' or 'fuzzylite' (the dialect of hedge codes)", got=hedges)
    return hedges


def _strip_comment(line: str) -> str:
    """``line`` up to a ``%`` or ``#`` outside quotes (a trailing comment), stripped."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch in "%#":
            return line[:i].strip()
    return line.strip()


def _warn(path, line, key, text) -> None:
    where = f"{path}:{line}: " if line is not None else f"{path}: "
    warnings.warn(f"{where}{key}: {text}", FisWarning, stacklevel=4)


def _indices(text: str) -> bool:
    """True for numbers separated by spaces or single commas (a trailing comma allowed), at least one."""
    body = text.strip()
    if body.endswith(","):
        body = body[:-1]
    tokens = re.split(r"\s*,\s*|\s+", body.strip())
    return bool(body.strip()) and all(_NUM_RE.fullmatch(t) for t in tokens)


class _RuleMatch:
    """The parts of a rule line ``i1 .. in, o1 .. om (weight) : connective`` (the groups 1-4 of a match)."""

    def __init__(self, parts):
        self.parts = parts

    def group(self, k: int) -> str:
        return self.parts[k - 1]


class _RuleLine:
    """A rule line's parser in linear time (a backtracking pattern took seconds on a garbled line)."""

    @staticmethod
    def match(line: str) -> _RuleMatch | None:
        head, sep, connective = line.rpartition(":")
        connective = connective.strip()
        if not sep or not connective or re.search(r"\s", connective):
            return None
        head = head.rstrip()
        if not head.endswith(")") or "(" not in head:
            return None
        i = head.rfind("(")
        weight, body = head[i + 1 : -1].strip(), head[:i]
        if not _NUM_RE.fullmatch(weight):
            return None
        pieces = body.split(",")
        for k in range(1, len(pieces)):  # the first comma with numbers on both sides splits them
            ante, cons = ",".join(pieces[:k]), ",".join(pieces[k:])
            if _indices(ante) and _indices(cons):
                return _RuleMatch((ante, cons, weight, connective))
        return None


_RULE_LINE = _RuleLine()


class _Section:
    def __init__(self, name, line):
        self.name, self.line, self.items, self.rules = name, line, {}, []


def _err(path, line, key, expected, got=None, show_got=True):
    return ConfigError(key, expected, got=got, file=str(path), line=line, show_got=show_got)


def _sections(text: str, path) -> list:
    sections = []
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line[0] in "%#":
            continue
        line = _strip_comment(line)
        if not line:
            continue
        if line.startswith("["):
            m = re.fullmatch(r"\[(System|Input\d+|Output\d+|Rules)\]", line)
            if not m:
                raise _err(path, n, "section", "[System], [InputN], [OutputN] or [Rules]", line)
            if any(s.name == m.group(1) for s in sections):
                raise _err(path, n, "section", f"each section once; [{m.group(1)}] repeats", None, False)
            sections.append(_Section(m.group(1), n))
            continue
        if not sections:
            raise _err(path, n, "file", "a [System] section first", line)
        sec = sections[-1]
        if sec.name == "Rules":
            sec.rules.append((n, line))
            continue
        if "=" not in line:
            raise _err(path, n, f"[{sec.name}]", "key=value", line)
        key, value = (s.strip() for s in line.split("=", 1))
        if key in sec.items:
            raise _err(path, n, f"[{sec.name}] {key}", "each key once (repeated)", None, False)
        sec.items[key] = (value, n)
    if not sections:
        raise _err(path, None, "file", "a [System] section (the file is empty)", None, False)
    return sections


def _item(sec, key, path, required, form=None):
    """``(value text, line)`` of ``key`` in a section; None when absent and not required."""
    if key not in sec.items:
        if required:
            raise _err(
                path, sec.line, f"[{sec.name}] {key}", f"a {form or key + '='} line in this section", None, False
            )
        return None
    return sec.items[key]


def _string(sec, key, path, required=True):
    item = _item(sec, key, path, required)
    if item is None:
        return None
    value, n = item
    if len(value) < 2 or value[0] not in "'\"" or value[-1] != value[0]:
        raise _err(path, n, f"[{sec.name}] {key}", "a quoted string like 'text'", value)
    return value[1:-1]


def _int(sec, key, path, required=True):
    item = _item(sec, key, path, required)
    if item is None:
        return None
    value, n = item
    if not re.fullmatch(r"\d+", value):
        raise _err(path, n, f"[{sec.name}] {key}", "a non-negative integer", value)
    return int(value)


def _numbers(text, path, n, key, expected):
    try:
        return [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise _err(path, n, key, expected, text) from None


def _method(sec, key, allowed, default, path):
    """The method named by ``key`` (``default`` when absent); ``""`` for an empty name (``AndMethod=''``)."""
    value = _string(sec, key, path, required=False)
    if value is None:
        return default
    value = _DEFUZZ_ALIASES.get(value, value) if key == "DefuzzMethod" else value
    if value not in allowed and not (value == "" and key in ("AndMethod", "OrMethod")):
        raise _err(path, sec.items[key][1], f"[System] {key}", f"one of {', '.join(allowed)}", value)
    return value


def _numbered(found: list, num: int | None) -> bool:
    """True when the sorted numbers ``found`` are exactly 1 .. ``num`` (a huge ``num`` costs nothing)."""
    return len(found) == num and all(k == i for i, k in enumerate(found, start=1))


def _flag(sec, key, path) -> float:
    """The number of a fuzzylite switch (``Enabled=1``, ``LockRange=0`` ...)."""
    text, n = sec.items[key]
    vals = _numbers(text, path, n, f"[{sec.name}] {key}", "0 or 1")
    if len(vals) != 1:
        raise _err(path, n, f"[{sec.name}] {key}", "0 or 1", text)
    return vals[0]


def _extra_keys(sec, path, output: bool) -> dict:
    """Warn about (or refuse) the keys this reader does not use; returns fuzzylite's switches read."""
    switches = {}
    for key, (text, n) in sec.items.items():
        where = f"[{sec.name}] {key}"
        if key in _VAR_KEYS or re.fullmatch(r"MF\d+", key) or (output and key == "Default"):
            continue
        if key in ("Enabled", "EnabledVariable"):
            if _flag(sec, key, path) != 1:
                raise _err(path, n, where, "1 (a disabled variable is not supported: remove it)", text)
            _warn(path, n, where, "ignored (variables are always enabled)")
        elif key == "LockPrevious":
            if _flag(sec, key, path) != 0:
                raise _err(path, n, where, "0 (keeping the previous output when no rule fires is not supported)", text)
            _warn(path, n, where, "ignored (0: no previous value kept)")
        elif key == "LockRange":
            switches[key] = (_flag(sec, key, path), n)  # checked once the terms are known
        else:
            _warn(path, n, where, "unknown key, ignored")
    return switches


def _variable(sec, path, output: bool) -> Variable:
    switches = _extra_keys(sec, path, output)
    name = _string(sec, "Name", path)
    text, n = _item(sec, "Range", path, True, form="Range=[lo hi]")
    m = re.fullmatch(r"\[(.*)\]", text)
    rng = _numbers(m.group(1), path, n, f"[{sec.name}] Range", "[lo hi] with two numbers") if m else None
    if rng is None or len(rng) != 2 or not rng[0] < rng[1] or not all(map(math.isfinite, rng)):
        raise _err(path, n, f"[{sec.name}] Range", "[lo hi] with two finite numbers lo < hi", text)
    if max(map(abs, rng)) > LIMIT:
        raise _err(path, n, f"[{sec.name}] Range", f"[lo hi] with {RANGE_TEXT[4:]}", text)
    num = _int(sec, "NumMFs", path)
    keys = sorted((k for k in sec.items if re.fullmatch(r"MF\d+", k)), key=lambda k: int(k[2:]))
    if not _numbered([int(k[2:]) for k in keys], num):
        raise _err(
            path,
            sec.items["NumMFs"][1],
            f"[{sec.name}] NumMFs",
            f"MF1 .. MF{num} to follow (NumMFs={num})",
            f"{', '.join(keys) or 'no MF lines'}",
        )
    terms = {k: _term(sec, k, path) for k in keys}
    names = {}
    for k, (term, _) in terms.items():
        if term in names:
            raise _err(path, sec.items[k][1], f"[{sec.name}] {k}", "distinct term names", term)
        if hasattr(torch.nn.ModuleDict, term):  # nn.ModuleDict refuses keys such as half, float, train
            raise _err(
                path, sec.items[k][1], f"[{sec.name}] {k}", "a term name that is not a torch Module method", term
            )
        names[term] = k
    terms = dict(terms.values())
    default = None
    if output and "Default" in sec.items:
        text, n = sec.items["Default"]
        vals = _numbers(text, path, n, f"[{sec.name}] Default", "a number")
        if len(vals) != 1 or math.isinf(vals[0]):
            raise _err(path, n, f"[{sec.name}] Default", "one finite number", text)
        if math.isnan(vals[0]):
            _warn(path, n, f"[{sec.name}] Default", "nan read as the middle of the range (MATLAB's default)")
        else:
            default = vals[0]
    if "LockRange" in switches:
        lock, n = switches["LockRange"]
        where = f"[{sec.name}] LockRange"
        if lock not in (0, 1):
            raise _err(path, n, where, "0 or 1", sec.items["LockRange"][0])
        outside = [t for t, mf in terms.items() if mf.is_singleton and not rng[0] <= mf.values()[0] <= rng[1]]
        if default is not None and not rng[0] <= default <= rng[1]:
            outside.insert(0, f"Default={default:g}")
        if lock == 1 and output and outside:
            raise _err(
                path,
                n,
                where,
                "0, or outputs that cannot leave Range (LockRange=1 would clip them; not supported)",
                f"1 with {', '.join(outside)} outside [{rng[0]:g} {rng[1]:g}]",
            )
        why = "outputs stay in Range" if output else "inputs are clipped to Range"
        _warn(path, n, where, f"ignored ({why} already)" if lock == 1 else "ignored (0: no clipping)")
    try:
        return Variable(name, rng, terms, default=default)
    except ConfigError as e:
        raise _err(path, sec.line, f"[{sec.name}] {e.key}", e.expected, e.got) from None


def _term(sec, k, path):
    """``(term name, membership function)`` of the line ``MFk=...``."""
    text, n = sec.items[k]
    where = f"[{sec.name}] {k}"
    m = _MF_LINE.match(text)
    if not m:
        raise _err(path, n, where, "'name':'type',[params]", text)
    term, kind, quoted, params = m.groups()
    kind = kind.strip()
    if kind not in _MF_READ:
        raise _err(path, n, where, f"a membership type ({', '.join(_MF_READ)})", kind)
    if not quoted:
        _warn(path, n, where, f"'{kind} lacks its closing quote (as fuzzylite's exporter writes it); read as '{kind}'")
    cls, order, lenient = _MF_READ[kind]
    values = _numbers(params, path, n, where, f"numeric parameters for {kind}")
    if cls is Discrete:
        if len(values) < 2 or len(values) % 2:
            raise _err(path, n, where, "pairs x1 y1 x2 y2 ... for discretemf (an even count)", f"[{params}]")
        order = tuple(range(len(values)))
    elif order is None:
        order = tuple(range(len(cls.names)))
    if len(values) > len(order) and lenient:
        extra = " ".join(_num(v, torch.float64) for v in values[len(order) :])
        _warn(path, n, where, f"{kind} takes {len(order)} parameters; the extra [{extra}] ignored (as MATLAB does)")
        values = values[: len(order)]
    if len(values) != len(order):
        raise _err(path, n, where, f"{len(order)} parameters for {kind}", f"[{params}]")
    if not all(math.isfinite(v) and abs(v) <= LIMIT for v in values):
        raise _err(path, n, where, "finite parameters of magnitude <= 1e30 (float32 arithmetic)", f"[{params}]")
    ours = [values[order.index(j)] for j in range(len(order))]
    try:
        return term, cls(*ours)
    except ConfigError as e:
        raise _err(path, n, where, e.expected, values) from None


def _clause(code: float, var: Variable, path, n, where, dialect: str, consequent: bool) -> Clause | None:
    if code == 0:
        return None
    neg = code < 0
    a = abs(code)
    idx = math.floor(a + 1e-9)
    hundredths = (a - idx) * 100
    frac = round(hundredths)
    codes = _HEDGE_CODES[dialect]
    if abs(hundredths - frac) > 1e-6 or frac not in codes:
        raise _err(path, n, where, f"a hedge code {_CODES_TEXT[dialect]}", code)
    hedges = codes[frac]
    if idx == 0 and hedges == ("any",):
        idx = 1  # fuzzylite's 0.99: "any", no term (the term does not matter)
    if not 1 <= idx <= len(var.terms):
        raise _err(path, n, where, f"an index 1..{len(var.terms)} of {var.name}'s terms (0 = unused)", code)
    if consequent and dialect == "fuzzylite" and (neg or hedges):
        raise _err(
            path,
            n,
            where,
            "an output index without hedge or sign in the fuzzylite dialect (fuzzylite hedges the rule's "
            "activation, this engine the output term)",
            code,
        )
    return Clause(var.name, var.term_names[idx - 1], hedges=(("not",) if neg else ()) + hedges)


def _distinct_names(by: dict, counts: dict, variables: list, path) -> None:
    """Refuse a variable name given twice, naming the second ``Name`` line."""
    sections = [by[f"Input{k}"] for k in range(1, counts["Input"] + 1)]
    sections += [by[f"Output{k}"] for k in range(1, counts["Output"] + 1)]
    seen = {}
    for sec, var in zip(sections, variables):
        if var.name in seen:
            raise _err(
                path,
                sec.items["Name"][1],
                f"[{sec.name}] Name",
                f"a name no other input or output has ([{seen[var.name]}] is named so too)",
                var.name,
            )
        seen[var.name] = sec.name


def _rules(rsec, sysec, inputs, outputs, methods: dict, path, dialect: str) -> list:
    """The rules of the ``[Rules]`` section; an empty And/OrMethod is refused when a rule joins inputs with it."""
    rules = []
    ni, no = len(inputs), len(outputs)
    for n, line in rsec.rules:
        m = _RULE_LINE.match(line)
        if not m:
            raise _err(path, n, "[Rules]", f"'i1 .. i{ni}, o1 .. o{no} (weight) : 1|2'", line)
        ante = _numbers(m.group(1), path, n, "[Rules]", "numbers")
        cons = _numbers(m.group(2), path, n, "[Rules]", "numbers")
        if len(ante) != ni or len(cons) != no:
            raise _err(path, n, "[Rules]", f"{ni} input and {no} output indices", f"{len(ante)} and {len(cons)}")
        weight = float(m.group(3))
        if not 0 <= weight <= 1:
            raise _err(path, n, "[Rules] weight", "a number in [0, 1]", weight)
        if m.group(4) not in ("1", "2"):
            raise _err(path, n, "[Rules] connective", "1 (AND) or 2 (OR) after the colon", m.group(4))
        where = f"[Rules] rule {len(rules) + 1}"
        a = [_clause(x, var, path, n, where, dialect, False) for x, var in zip(ante, inputs)]
        c = [_clause(x, var, path, n, where, dialect, True) for x, var in zip(cons, outputs)]
        a, c = [x for x in a if x is not None], [x for x in c if x is not None]
        if not a:  # fuzzylite writes a rule on an output (a chained system) so, and drops it on reading
            _warn(path, n, "[Rules]", "a rule without an input condition (all input indices 0): skipped")
            continue
        if not c:
            raise _err(path, n, where, "at least one output index that is not 0", line)
        connective = "and" if m.group(4) == "1" else "or"
        if len(a) > 1 and methods[f"{connective}_method"] == "":
            key = "AndMethod" if connective == "and" else "OrMethod"
            raise _err(path, sysec.items[key][1], f"[System] {key}", f"a method ({where} joins inputs with it)", "''")
        rules.append(Rule(a, c, connective=connective, weight=weight))
    for connective, key, default in (("and", "AndMethod", "min"), ("or", "OrMethod", "max")):
        if methods[f"{connective}_method"] == "":
            _warn(path, sysec.items[key][1], f"[System] {key}", f"empty (no rule uses it), read as '{default}'")
            methods[f"{connective}_method"] = default
    return rules


def parse_fis(text: str, *, path="<string>", hedges: str = "octave") -> MamdaniSystem:
    """A :class:`MamdaniSystem` from the text of a ``.fis`` file.

    Args:
        text: the file's text.
        path: names the file in errors and warnings.
        hedges: the dialect of the rules' hedge codes, ``"octave"`` or ``"fuzzylite"`` (module docstring).
    """
    dialect = _dialect(hedges)
    sections = _sections(text, path)
    by = {s.name: s for s in sections}
    if "System" not in by:
        raise _err(path, sections[0].line, "file", "a [System] section", f"[{sections[0].name}] first")
    sysec = by["System"]
    for key, (value, n) in sysec.items.items():
        if key == "TypeReductionMethod":
            raise _err(path, n, "[System] TypeReductionMethod", "a type-1 system (type-2 is not supported)", value)
        if key not in _SYSTEM_KEYS:
            _warn(path, n, f"[System] {key}", "unknown key, ignored")
    name = _string(sysec, "Name", path)
    kind = _string(sysec, "Type", path, required=False) or "mamdani"
    if kind.lower() != "mamdani":
        what = f"{kind[:1].upper()}{kind[1:]} systems are not supported"
        raise _err(path, sysec.items["Type"][1], "[System] Type", f"'mamdani' ({what})", kind)
    counts = {}
    for key, prefix in (("NumInputs", "Input"), ("NumOutputs", "Output")):
        num = _int(sysec, key, path)
        found = sorted(int(s.name[len(prefix) :]) for s in sections if re.fullmatch(prefix + r"\d+", s.name))
        if not _numbered(found, num):
            raise _err(
                path,
                sysec.items[key][1],
                f"[System] {key}",
                f"sections [{prefix}1] .. [{prefix}{num}]",
                ", ".join(f"[{prefix}{k}]" for k in found) or "none",
            )
        if num == 0:
            raise _err(path, sysec.items[key][1], f"[System] {key}", "at least 1", num)
        counts[prefix] = num
    inputs = [_variable(by[f"Input{k}"], path, False) for k in range(1, counts["Input"] + 1)]
    outputs = [_variable(by[f"Output{k}"], path, True) for k in range(1, counts["Output"] + 1)]
    _distinct_names(by, counts, inputs + outputs, path)
    methods = dict(
        and_method=_method(sysec, "AndMethod", AND_METHODS, "min", path),
        or_method=_method(sysec, "OrMethod", OR_METHODS, "max", path),
        implication=_method(sysec, "ImpMethod", IMPLICATIONS, "min", path),
        aggregation=_method(sysec, "AggMethod", AGGREGATIONS, "max", path),
        defuzzification=_method(sysec, "DefuzzMethod", DEFUZZIFIERS, "centroid", path),
    )
    resolution = _int(sysec, "Resolution", path, required=False)
    if resolution is not None:
        methods["resolution"] = resolution
    if "Rules" not in by:
        raise _err(path, sections[-1].line, "file", "a [Rules] section", None, False)
    rules = _rules(by["Rules"], sysec, inputs, outputs, methods, path, dialect)
    num_rules = _int(sysec, "NumRules", path, required=False)
    lines = len(by["Rules"].rules)
    if num_rules is not None and num_rules != lines:
        raise _err(path, sysec.items["NumRules"][1], "[System] NumRules", f"{lines} (the rule lines found)", num_rules)
    if not rules:
        raise _err(path, by["Rules"].line, "[Rules]", "at least one rule line", None, False)
    try:
        return MamdaniSystem(name, inputs, outputs, rules, **methods)
    except ConfigError as e:
        line = sysec.items["Resolution"][1] if e.key == "resolution" and "Resolution" in sysec.items else sysec.line
        raise _err(
            path, line, "[System] Resolution" if e.key == "resolution" else e.key, e.expected, e.got, e.show_got
        ) from None


def read_fis(path, *, hedges: str = "octave") -> MamdaniSystem:
    """Read a ``.fis`` file into a :class:`MamdaniSystem` (``hedges``: the rules' dialect, see :func:`parse_fis`)."""
    dialect = _dialect(hedges)
    p = Path(path)
    text = read_text(p, "file", what=".fis file")
    return parse_fis(text, path=p, hedges=dialect)


def _num(v: float, dtype) -> str:
    """The shortest text that reads back to the same value in ``dtype``."""
    v = float(v)
    if v.is_integer() and abs(v) < 1e15:
        return str(int(v))
    return str(np.float32(v)) if dtype == torch.float32 else repr(v)


def _code(clause: Clause | None, var: Variable, where: str, dialect: str, consequent: bool) -> str:
    if clause is None:
        return "0"
    hedges = tuple(clause.hedges)
    neg = hedges[:1] == ("not",)
    rest = hedges[1:] if neg else hedges
    codes = _CODE_OF[dialect]
    if (rest and rest not in codes) or (consequent and dialect == "fuzzylite" and hedges):
        expected = (
            f"hedges that .fis can encode in the {dialect} dialect ({_HEDGE_NAMES[dialect]})"
            if not consequent or dialect != "fuzzylite"
            else "no hedge on an output in the fuzzylite dialect (fuzzylite hedges the rule's activation)"
        )
        raise ConfigError(where, expected, got=" ".join([clause.variable, "IS", *hedges, clause.term]))
    idx = var.index(clause.term) + 1
    if rest == ("any",):
        idx = 0  # fuzzylite's 0.99: "any" takes no term
    text = str(idx) if not rest else f"{idx}.{codes[rest]:02d}".rstrip("0")
    return ("-" if neg else "") + text


def fis_text(system: MamdaniSystem, *, comments: str = "", hedges: str = "octave") -> str:
    """The ``.fis`` text of a system.

    Args:
        system: the system.
        comments: lines written first, each prefixed ``% ``.
        hedges: the dialect of the hedge codes, ``"octave"`` or ``"fuzzylite"``; a hedge it
            cannot encode is a :class:`ConfigError` naming the rule.
    """
    dialect = _dialect(hedges)
    out = [f"% {c}" if c else "%" for c in comments.splitlines()]
    out += [
        "[System]",
        f"Name='{system.name}'",
        "Type='mamdani'",
        "Version=2.0",
        f"NumInputs={len(system.inputs)}",
        f"NumOutputs={len(system.outputs)}",
        f"NumRules={len(system.rules)}",
        f"AndMethod='{system.and_method}'",
        f"OrMethod='{system.or_method}'",
        f"ImpMethod='{system.implication}'",
        f"AggMethod='{system.aggregation}'",
        f"DefuzzMethod='{system.defuzzification}'",
    ]
    if system.resolution != 1000:
        out.append(f"Resolution={system.resolution}")
    for label, variables in (("Input", system.inputs), ("Output", system.outputs)):
        for k, var in enumerate(variables, start=1):
            out += [
                "",
                f"[{label}{k}]",
                f"Name='{var.name}'",
                f"Range=[{_num(var.range[0], torch.float64)} {_num(var.range[1], torch.float64)}]",
                f"NumMFs={len(var.terms)}",
            ]
            for j, (term, mf) in enumerate(var.terms.items(), start=1):
                mname, order = _MF_WRITE[mf.kind]
                ours = mf.values()
                matlab = ours if order is None else [ours[i] for i in order]
                dtype = mf.raw.dtype
                out.append(f"MF{j}='{term}':'{mname}',[{' '.join(_num(v, dtype) for v in matlab)}]")
            if label == "Output" and var.default != 0.5 * (var.range[0] + var.range[1]):
                out.append(f"Default={_num(var.default, torch.float64)}")
    out += ["", "[Rules]"]
    for r, rule in enumerate(system.rules, start=1):
        where = f"rule {r} ({rule})"
        ante = {c.variable: c for c in rule.antecedent}
        if len(ante) != len(rule.antecedent):
            raise ConfigError(where, ".fis rules use each input at most once", got=str(rule))
        cons = {c.variable: c for c in rule.consequent}
        a = " ".join(_code(ante.get(v.name), v, where, dialect, False) for v in system.inputs)
        c = " ".join(_code(cons.get(v.name), v, where, dialect, True) for v in system.outputs)
        out.append(f"{a}, {c} ({_num(rule.weight, torch.float64)}) : {1 if rule.connective == 'and' else 2}")
    return "\n".join(out) + "\n"


def write_fis(system: MamdaniSystem, path, *, comments: str = "", hedges: str = "octave") -> Path:
    """Write a system as a ``.fis`` file; returns the path.

    Reading it back with :func:`read_fis` and the same ``hedges`` dialect gives a system with
    identical outputs.
    """
    text = fis_text(system, comments=comments, hedges=hedges)
    p = Path(path)
    p.write_text(text, encoding="utf-8")
    return p

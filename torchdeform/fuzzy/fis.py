"""MATLAB ``.fis`` files: read and write Mamdani systems.

The format (Fuzzy Logic Toolbox), as read here::

    % comment lines start with % or #
    [System]
    Name='tissue'
    Type='mamdani'
    NumInputs=1
    NumOutputs=2
    NumRules=7
    AndMethod='min'          min | prod
    OrMethod='max'           max | probor
    ImpMethod='min'          min | prod
    AggMethod='max'          max | sum | probor
    DefuzzMethod='centroid'  centroid | bisector | mom | som | lom

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
index means NOT; the fractional part encodes a hedge: ``.01`` seldom, ``.05`` somewhat, ``.2``
very, ``.3`` extremely, ``.4`` very very, ``.99`` any. Parameter orders are MATLAB's
(``gaussmf [sigma c]``, ``gbellmf [a b c]``, ``sigmf [a c]`` with slope ``a`` and center
``c``); ``singletonmf [v]`` is our extension for singleton terms, and ``Default=v`` in an
output section (also ours) sets the value used when no rule fires (MATLAB's mid-range when
absent). ``Version``, ``DisableStructuralChecks`` and the ``Resolution`` key (ours, grid cells
per output) are accepted in ``[System]``.

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
from pathlib import Path

import numpy as np
import torch

from ..checks import read_text
from ..errors import ConfigError
from .membership import Bell, Gaussian, Sigmoid, Singleton, Trapezoid, Triangle
from .rules import LIMIT, RANGE_TEXT, Clause, Rule, Variable
from .system import AGGREGATIONS, AND_METHODS, DEFUZZIFIERS, IMPLICATIONS, OR_METHODS, MamdaniSystem

__all__ = ["parse_fis", "read_fis", "fis_text", "write_fis"]

# MATLAB name -> (our class, MATLAB parameter order as indices into our order)
_MF_READ = {
    "trapmf": (Trapezoid, (0, 1, 2, 3)),
    "trimf": (Triangle, (0, 1, 2)),
    "gaussmf": (Gaussian, (1, 0)),  # [sigma c] -> (mean, sigma)
    "gbellmf": (Bell, (0, 1, 2)),
    "sigmf": (Sigmoid, (1, 0)),  # [a c] = [slope center] -> (center, slope)
    "singletonmf": (Singleton, (0,)),
}
_MF_WRITE = {cls.kind: (name, order) for name, (cls, order) in _MF_READ.items()}

_HEDGE_CODES = {1: ("seldom",), 5: ("somewhat",), 20: ("very",), 30: ("extremely",), 40: ("very", "very"), 99: ("any",)}
_CODE_OF = {h: c for c, h in _HEDGE_CODES.items()}

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
_MF_LINE = re.compile(r"^'([^']*)'\s*:\s*'([^']*)'\s*,\s*\[([^\]]*)\]$")
_NUM_RE = re.compile(_NUM)


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
    if len(value) < 2 or value[0] != "'" or value[-1] != "'":
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
    value = _string(sec, key, path, required=False)
    if value is None:
        return default
    if value not in allowed:
        raise _err(path, sec.items[key][1], f"[System] {key}", f"one of {', '.join(allowed)}", value)
    return value


def _numbered(found: list, num: int | None) -> bool:
    """True when the sorted numbers ``found`` are exactly 1 .. ``num`` (a huge ``num`` costs nothing)."""
    return len(found) == num and all(k == i for i, k in enumerate(found, start=1))


def _variable(sec, path, output: bool) -> Variable:
    for key, (_, n) in sec.items.items():
        if key not in _VAR_KEYS and not re.fullmatch(r"MF\d+", key) and not (output and key == "Default"):
            raise _err(
                path,
                n,
                f"[{sec.name}] {key}",
                f"one of Name, Range, NumMFs, MFk{', Default' if output else ''}",
                None,
                False,
            )
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
    terms = {}
    for k in keys:
        text, n = sec.items[k]
        m = _MF_LINE.match(text)
        if not m:
            raise _err(path, n, f"[{sec.name}] {k}", "'name':'type',[params]", text)
        term, kind, params = m.groups()
        if kind not in _MF_READ:
            raise _err(path, n, f"[{sec.name}] {k}", f"a membership type ({', '.join(_MF_READ)})", kind)
        cls, order = _MF_READ[kind]
        values = _numbers(params, path, n, f"[{sec.name}] {k}", f"numeric parameters for {kind}")
        if len(values) != len(order):
            raise _err(path, n, f"[{sec.name}] {k}", f"{len(order)} parameters for {kind}", f"[{params}]")
        if not all(math.isfinite(v) and abs(v) <= LIMIT for v in values):
            raise _err(
                path,
                n,
                f"[{sec.name}] {k}",
                "finite parameters of magnitude <= 1e30 (float32 arithmetic)",
                f"[{params}]",
            )
        if term in terms:
            raise _err(path, n, f"[{sec.name}] {k}", "distinct term names", term)
        ours = [values[order.index(j)] for j in range(len(order))]
        try:
            terms[term] = cls(*ours)
        except ConfigError as e:
            raise _err(path, n, f"[{sec.name}] {k}", e.expected, values) from None
    default = None
    if output and "Default" in sec.items:
        text, n = sec.items["Default"]
        vals = _numbers(text, path, n, f"[{sec.name}] Default", "a number")
        if len(vals) != 1 or not math.isfinite(vals[0]):
            raise _err(path, n, f"[{sec.name}] Default", "one finite number", text)
        default = vals[0]
    try:
        return Variable(name, rng, terms, default=default)
    except ConfigError as e:
        raise _err(path, sec.line, f"[{sec.name}] {e.key}", e.expected, e.got) from None


def _clause(code: float, var: Variable, path, n, where) -> Clause | None:
    if code == 0:
        return None
    neg = code < 0
    a = abs(code)
    idx = math.floor(a + 1e-9)
    frac = round((a - idx) * 100)
    if frac not in _HEDGE_CODES and frac != 0:
        raise _err(path, n, where, "a hedge code .01 .05 .2 .3 .4 or .99 after the index", code)
    if not 1 <= idx <= len(var.terms):
        raise _err(path, n, where, f"an index 1..{len(var.terms)} of {var.name}'s terms (0 = unused)", code)
    hedges = (("not",) if neg else ()) + _HEDGE_CODES.get(frac, ())
    return Clause(var.name, var.term_names[idx - 1], hedges=hedges)


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


def parse_fis(text: str, *, path="<string>") -> MamdaniSystem:
    """A :class:`MamdaniSystem` from the text of a ``.fis`` file (``path`` names it in errors)."""
    sections = _sections(text, path)
    by = {s.name: s for s in sections}
    if "System" not in by:
        raise _err(path, sections[0].line, "file", "a [System] section", f"[{sections[0].name}] first")
    sysec = by["System"]
    for key, (_, n) in sysec.items.items():
        if key not in _SYSTEM_KEYS:
            raise _err(path, n, f"[System] {key}", f"one of {', '.join(sorted(_SYSTEM_KEYS))}", None, False)
    name = _string(sysec, "Name", path)
    kind = _string(sysec, "Type", path, required=False) or "mamdani"
    if kind.lower() != "mamdani":
        raise _err(path, sysec.items["Type"][1], "[System] Type", "'mamdani' (Sugeno systems are not supported)", kind)
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
    rules = []
    ni, no = len(inputs), len(outputs)
    for n, line in by["Rules"].rules:
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
        a = [c for c in (_clause(x, var, path, n, where) for x, var in zip(ante, inputs)) if c is not None]
        c = [c for c in (_clause(x, var, path, n, where) for x, var in zip(cons, outputs)) if c is not None]
        if not a:
            raise _err(path, n, where, "at least one input index that is not 0", line)
        if not c:
            raise _err(path, n, where, "at least one output index that is not 0", line)
        rules.append(Rule(a, c, connective="and" if m.group(4) == "1" else "or", weight=weight))
    num_rules = _int(sysec, "NumRules", path, required=False)
    if num_rules is not None and num_rules != len(rules):
        raise _err(
            path, sysec.items["NumRules"][1], "[System] NumRules", f"{len(rules)} (the rule lines found)", num_rules
        )
    if not rules:
        raise _err(path, by["Rules"].line, "[Rules]", "at least one rule line", None, False)
    try:
        return MamdaniSystem(name, inputs, outputs, rules, **methods)
    except ConfigError as e:
        line = sysec.items["Resolution"][1] if e.key == "resolution" and "Resolution" in sysec.items else sysec.line
        raise _err(
            path, line, "[System] Resolution" if e.key == "resolution" else e.key, e.expected, e.got, e.show_got
        ) from None


def read_fis(path) -> MamdaniSystem:
    """Read a MATLAB ``.fis`` file into a :class:`MamdaniSystem`."""
    p = Path(path)
    text = read_text(p, "file", what=".fis file")
    return parse_fis(text, path=p)


def _num(v: float, dtype) -> str:
    """The shortest text that reads back to the same value in ``dtype``."""
    v = float(v)
    if v.is_integer() and abs(v) < 1e15:
        return str(int(v))
    return str(np.float32(v)) if dtype == torch.float32 else repr(v)


def _code(clause: Clause | None, var: Variable, where: str) -> str:
    if clause is None:
        return "0"
    hedges = tuple(clause.hedges)
    neg = hedges[:1] == ("not",)
    rest = hedges[1:] if neg else hedges
    if rest and rest not in _CODE_OF:
        raise ConfigError(
            where,
            "hedges that .fis can encode (not, seldom, somewhat, very, extremely, very very, any)",
            got=" ".join(hedges),
        )
    idx = var.index(clause.term) + 1
    text = str(idx) if not rest else f"{idx}.{_CODE_OF[rest]:02d}".rstrip("0")
    return ("-" if neg else "") + text


def fis_text(system: MamdaniSystem, *, comments: str = "") -> str:
    """The ``.fis`` text of a system (``comments``: lines written first, each prefixed ``% ``)."""
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
                matlab = [ours[i] for i in order]
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
        a = " ".join(_code(ante.get(v.name), v, where) for v in system.inputs)
        c = " ".join(_code(cons.get(v.name), v, where) for v in system.outputs)
        out.append(f"{a}, {c} ({_num(rule.weight, torch.float64)}) : {1 if rule.connective == 'and' else 2}")
    return "\n".join(out) + "\n"


def write_fis(system: MamdaniSystem, path, *, comments: str = "") -> Path:
    """Write a system as a MATLAB ``.fis`` file; returns the path.

    Reading it back with :func:`read_fis` gives a system with identical outputs.
    """
    p = Path(path)
    p.write_text(fis_text(system, comments=comments), encoding="utf-8")
    return p

"""What ``torchdeform fuzzy show | eval | plot`` do, as functions (the CLI only parses).

    torchdeform fuzzy show FILE.fis                       variables, terms, rules
    torchdeform fuzzy eval FILE.fis NAME=VALUE ... [--json]
    torchdeform fuzzy eval FILE.fis --inputs FILE.csv [--json]
    torchdeform fuzzy plot FILE.fis --out DIR             membership functions, input-output curves

``FILE`` may also be the name of a shipped preset (``susilap_g``, ``robo_sim_ventricle`` ...).
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
from pathlib import Path

import torch

from ..checks import read_text
from ..errors import ConfigError
from ..outputs import save_figure
from .fis import DIALECTS, read_fis
from .system import MamdaniSystem

__all__ = [
    "load",
    "describe",
    "parse_assignments",
    "warn_out_of_range",
    "read_inputs_csv",
    "evaluate_rows",
    "format_rows",
    "plot",
    "main",
    "add_arguments",
]


def load(name_or_path, *, hedges: str = "octave") -> MamdaniSystem:
    """A system from a ``.fis`` path (``hedges``: its rule codes' dialect), or a preset name when no such file exists."""
    p = Path(name_or_path)
    if p.exists() or p.suffix == ".fis" or "/" in str(name_or_path):
        return read_fis(p, hedges=hedges)
    try:
        from .presets import load_preset
    except ImportError:  # the preset library has not landed yet
        raise ConfigError("file", "an existing .fis file (no presets are shipped yet)", got=str(name_or_path)) from None
    return load_preset(str(name_or_path))


def describe(fis: MamdaniSystem) -> str:
    """A readable summary: methods, variables with ranges and terms, numbered rules."""
    lines = [
        f"{fis.name}: Mamdani, {len(fis.inputs)} input(s), {len(fis.outputs)} output(s), {len(fis.rules)} rules",
        f"  AND {fis.and_method}, OR {fis.or_method}, implication {fis.implication}, "
        f"aggregation {fis.aggregation}, defuzzification {fis.defuzzification} "
        f"({fis.resolution} cells)",
        "",
    ]
    for label, variables in (("input", fis.inputs), ("output", fis.outputs)):
        for v in variables:
            extra = f", default {v.default:g}" if label == "output" else ""
            lines.append(f"{label} {v.name}  range [{v.range[0]:g}, {v.range[1]:g}]{extra}")
            width = max(len(t) for t in v.term_names)
            for t, mf in v.terms.items():
                params = " ".join(f"{n}={val:g}" for n, val in zip(mf.names, mf.values()))
                lines.append(f"  {t:<{width}}  {mf.kind:<9}  {params}")
            lines.append("")
    lines.append("rules")
    width = len(str(len(fis.rules)))
    lines += [f"  {k:>{width}}. {rule}" for k, rule in enumerate(fis.rules, start=1)]
    return "\n".join(lines)


def parse_assignments(fis: MamdaniSystem, items) -> dict:
    """``["consistency=5.5", ...]`` -> ``{"consistency": 5.5}``; every input exactly once."""
    values = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep:
            raise ConfigError("input", "NAME=VALUE", got=item)
        if name not in fis.input_names():
            raise ConfigError("input", f"one of {', '.join(fis.input_names())}", got=name)
        try:
            values[name] = float(text)
        except ValueError:
            raise ConfigError(name, "a number", got=text) from None
        if not math.isfinite(values[name]):
            raise ConfigError(name, "a finite number", got=text)
    missing = [n for n in fis.input_names() if n not in values]
    if missing:
        raise ConfigError(
            "inputs",
            f"a value for every input ({', '.join(fis.input_names())})",
            got=f"missing {', '.join(missing)}",
            show_got=True,
        )
    return values


def read_inputs_csv(fis: MamdaniSystem, path) -> torch.Tensor:
    """Rows ``(N, n_inputs)`` from a CSV file whose header names the inputs.

    Extra columns are ignored; blank lines are skipped.
    """
    p = Path(path)
    with io.StringIO(read_text(p, "--inputs", what="CSV file"), newline="") as f:
        reader = csv.reader(f)
        header = [h.strip() for h in next(reader, [])]
        missing = [n for n in fis.input_names() if n not in header]
        if missing:
            raise ConfigError(
                "header",
                f"columns for every input ({', '.join(fis.input_names())})",
                got=f"missing {', '.join(missing)}",
                file=str(p),
                line=1,
            )
        cols = [header.index(n) for n in fis.input_names()]
        rows = []
        for line, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            try:
                values = [float(row[c]) for c in cols]
            except (ValueError, IndexError):
                raise ConfigError(
                    "row",
                    f"numbers in columns {', '.join(fis.input_names())}",
                    got=",".join(row),
                    file=str(p),
                    line=line,
                ) from None
            if not all(map(math.isfinite, values)):
                raise ConfigError("row", "finite numbers", got=",".join(row), file=str(p), line=line)
            rows.append(values)
    if not rows:
        raise ConfigError("--inputs", "at least one data row", got=str(p))
    return torch.tensor(rows, dtype=torch.float64)


def warn_out_of_range(fis: MamdaniSystem, x: torch.Tensor) -> None:
    """Warn (a :class:`~torchdeform.errors.ConfigWarning`, one per input) for values outside an input's range.

    ``x`` is ``(N, n_inputs)``. The rules were written for the range: outside it the result is
    an extrapolation of the edge's memberships, rarely what was meant (a unit mixed up).
    """
    import warnings

    from ..errors import ConfigWarning

    for i, v in enumerate(fis.inputs):
        lo, hi = v.range
        col = x[:, i]
        out = (col < lo) | (col > hi)
        if bool(out.any()):
            bad = col[out]
            where = f"{int(out.sum())} of {len(col)} rows" if len(col) > 1 else f"{float(bad[0]):g}"
            warnings.warn(
                f"input {v.name}: {where} outside its range [{lo:g}, {hi:g}]; the rules were written for that "
                "range (is a unit mixed up?)",
                ConfigWarning,
                stacklevel=2,
            )


def evaluate_rows(fis: MamdaniSystem, x: torch.Tensor) -> list:
    """One dict per row: inputs and crisp outputs (float64 evaluation)."""
    fis = fis.double()
    with torch.no_grad():
        y = fis(x.double())
    ins, outs = fis.input_names(), fis.output_names()
    return [dict(zip(ins, map(float, xr)), **dict(zip(outs, map(float, yr)))) for xr, yr in zip(x, y)]


def format_rows(fis: MamdaniSystem, rows: list, as_json: bool) -> str:
    """The rows of :func:`evaluate_rows` as CSV (a header, then ``%.6g`` values) or JSON (one row: one object)."""
    if as_json:
        return json.dumps(rows[0] if len(rows) == 1 else rows, indent=None)
    names = fis.input_names() + fis.output_names()
    out = [",".join(names)]
    out += [",".join(f"{r[n]:.6g}" for n in names) for r in rows]
    return "\n".join(out)


def plot(fis: MamdaniSystem, out_dir, *, points: int = 401) -> list:
    """Write PNGs of the membership functions and the input-output curves.

    ``mf_<variable>.png`` (every term of every variable) and ``curve_<input>_<output>.png``
    (each output against each input, the other inputs at the middle of their ranges).
    Returns the paths written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fis = fis.double()
    written = []
    with torch.no_grad():
        for v in list(fis.inputs) + list(fis.outputs):
            fig, ax = plt.subplots(figsize=(6, 3))
            xs = torch.linspace(v.range[0], v.range[1], points, dtype=torch.float64)
            for t, mf in v.terms.items():
                if mf.is_singleton:
                    ax.vlines(mf.values()[0], 0, 1, label=t)
                else:
                    ax.plot(xs, mf(xs), label=t)
            ax.set(xlabel=v.name, ylabel="membership", ylim=(-0.02, 1.05), title=f"{fis.name}: {v.name}")
            ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
            fig.tight_layout()
            path = out / f"mf_{v.name}.png"
            save_figure(fig, path, dpi=110)
            plt.close(fig)
            written.append(path)
        mid = torch.tensor([0.5 * (v.range[0] + v.range[1]) for v in fis.inputs], dtype=torch.float64)
        for i, v in enumerate(fis.inputs):
            xs = mid.repeat(points, 1)
            xs[:, i] = torch.linspace(v.range[0], v.range[1], points, dtype=torch.float64)
            ys = fis(xs)
            for o, w in enumerate(fis.outputs):
                fig, ax = plt.subplots(figsize=(5, 3.2))
                ax.plot(xs[:, i], ys[:, o])
                others = ", ".join(f"{u.name}={float(mid[k]):g}" for k, u in enumerate(fis.inputs) if k != i)
                ax.set(xlabel=v.name, ylabel=w.name, title=f"{fis.name}" + (f" ({others})" if others else ""))
                ax.grid(alpha=0.3)
                fig.tight_layout()
                path = out / f"curve_{v.name}_{w.name}.png"
                save_figure(fig, path, dpi=110)
                plt.close(fig)
                written.append(path)
    return written


def main(args) -> int:
    """Entry point of ``torchdeform fuzzy``; returns the exit status."""
    if args.fuzzy_command == "vocabulary":
        from .vocabulary import plot_kinds, vocabulary_table

        print(vocabulary_table())
        if args.out:
            out = Path(args.out)
            out.mkdir(parents=True, exist_ok=True)
            print(plot_kinds(out / "membership_kinds.png"), file=sys.stderr)
        return 0
    fis = load(args.file, hedges=args.hedges)
    if args.fuzzy_command == "show":
        print(describe(fis))
    elif args.fuzzy_command == "eval":
        if args.inputs and args.values:
            raise ConfigError(
                "eval", "either NAME=VALUE pairs or --inputs FILE.csv, not both", got=None, show_got=False
            )
        x = (
            read_inputs_csv(fis, args.inputs)
            if args.inputs
            else torch.tensor(
                [[parse_assignments(fis, args.values)[n] for n in fis.input_names()]], dtype=torch.float64
            )
        )
        warn_out_of_range(fis, x)
        print(format_rows(fis, evaluate_rows(fis, x), args.json))
    else:
        for path in plot(fis, args.out):
            print(path)
    return 0


def add_arguments(parser) -> None:
    """The ``fuzzy`` sub-commands."""
    sub = parser.add_subparsers(dest="fuzzy_command", required=True, metavar="COMMAND")
    s = sub.add_parser("show", help="variables, terms and rules of a rule file")
    s.add_argument("file", help=".fis file or preset name")
    e = sub.add_parser("eval", help="crisp outputs for inputs NAME=VALUE ... or --inputs FILE.csv")
    e.add_argument("file", help=".fis file or preset name")
    e.add_argument("values", nargs="*", metavar="NAME=VALUE")
    e.add_argument("--inputs", default=None, help="CSV file whose header names the inputs; one result per row")
    e.add_argument("--json", action="store_true", help="print JSON instead of CSV")
    p = sub.add_parser("plot", help="membership functions and input-output curves as PNG")
    p.add_argument("file", help=".fis file or preset name")
    p.add_argument("--out", required=True, help="output folder")
    v = sub.add_parser(
        "vocabulary", help="the membership kinds, hedges and operators read here, against MATLAB, Octave, ..."
    )
    v.add_argument("--out", default=None, help="also draw every membership kind: OUT/membership_kinds.png")
    for command in (s, e, p):
        command.add_argument(
            "--hedges",
            choices=DIALECTS,
            default="octave",
            help="what the fraction of a rule's term index means: Octave's hedge powers (default) or "
            "fuzzylite's hedge codes (.01 seldom, .3 extremely, .99 any)",
        )

"""The command line's contract: typed option values, one-line errors, and what each exit status means.

* ``0``: the command did what was asked, and every output it wrote is whole and finite.
* ``2``: the command refused, before or during the work, with one line on stderr naming the file,
  line, key or option and what was expected (bad input, a missing or unwritable path, not enough
  memory, a run that diverged). Earlier outputs are left as they were.
* ``130``: interrupted (Ctrl-C); earlier outputs are left as they were.
* ``1`` with a traceback: a bug in torchdeform. Please report it with the command line, the input
  files and the traceback.

The pieces:

* :class:`Parser`: an :class:`argparse.ArgumentParser` whose usage errors are one line.
* option types: :func:`integer`, :func:`number`, :func:`int_list` refuse what the library would
  choke on (``--dt nan``, ``--dt 0``, ``--threads 0``) while the command line is read.
* :func:`guarded`: runs a command and turns what a user can cause into one line and exit status 2
  (also used by the training scripts), with warnings shown as one line each.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import traceback
import warnings
from contextlib import contextmanager

__all__ = ["Parser", "integer", "number", "int_list", "number_list", "guarded", "one_line_warnings", "REPORT"]

#: what the bug line asks for
REPORT = "this is a bug in torchdeform: please report it with the command line, the input files and the traceback above"


class Parser(argparse.ArgumentParser):
    r"""An argument parser whose usage errors are one line (``prog: error: ... (see prog --help)``).

    Sub-command parsers made with ``add_subparsers`` are of this class too.

    Examples:
        >>> p = Parser(prog="demo")
        >>> _ = p.add_argument("--steps", type=integer(lo=1))
        >>> p.parse_args(["--steps", "40"]).steps
        40
        >>> import contextlib, io
        >>> err = io.StringIO()
        >>> with contextlib.redirect_stderr(err):
        ...     try:
        ...         p.parse_args(["--steps", "0"])
        ...     except SystemExit as e:
        ...         print(e.code)
        2
        >>> err.getvalue()
        'demo: error: argument --steps: expected an integer >= 1, got 0 (see demo --help)\n'
    """

    def __init__(self, **kwargs):
        # ``argparse.ArgumentParser``'s options, keyword-only (``prog=``, ``description=``, ...)
        super().__init__(**kwargs)

    def error(self, message):
        """Print ``message`` as one line and exit with status 2."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _bounds(lo, hi, lo_open, hi_open) -> str:
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    return " and ".join(parts)


def number(*, lo=None, hi=None, lo_open: bool = False, hi_open: bool = False, unit: str = ""):
    """An ``argparse`` type: a finite number within the bounds (``nan`` and ``inf`` are refused).

    Examples:
        >>> dt = number(lo=0, lo_open=True, unit="s")
        >>> dt("2e-4")
        0.0002
        >>> dt("nan")
        Traceback (most recent call last):
        ...
        argparse.ArgumentTypeError: expected a finite number > 0 (s), got 'nan'
    """
    bounds = _bounds(lo, hi, lo_open, hi_open)
    expected = "a finite number" + (f" {bounds}" if bounds else "") + (f" ({unit})" if unit else "")

    def parse(text):
        try:
            v = float(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if (
            not math.isfinite(v)
            or (lo is not None and (v < lo or (lo_open and v == lo)))
            or (hi is not None and (v > hi or (hi_open and v == hi)))
        ):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return v

    parse.__name__ = "number"
    return parse


def integer(*, lo=None, hi=None):
    """An ``argparse`` type: an integer within ``[lo, hi]``.

    Examples:
        >>> integer(lo=1)("3")
        3
        >>> integer(lo=1)("2.5")
        Traceback (most recent call last):
        ...
        argparse.ArgumentTypeError: expected an integer >= 1, got '2.5'
    """
    bounds = _bounds(lo, hi, False, False)
    expected = "an integer" + (f" {bounds}" if bounds else "")

    def parse(text):
        try:
            v = int(str(text).strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {v}")
        return v

    parse.__name__ = "integer"
    return parse


def int_list(*, lo=None, hi=None):
    """An ``argparse`` type: comma-separated integers within ``[lo, hi]``, at least one.

    Examples:
        >>> int_list(lo=2)("16,32, 64")
        [16, 32, 64]
        >>> int_list(lo=2)("16,x")
        Traceback (most recent call last):
        ...
        argparse.ArgumentTypeError: expected comma-separated integers >= 2 (e.g. 16,32,64), got '16,x'
    """
    bounds = _bounds(lo, hi, False, False)
    expected = "comma-separated integers" + (f" {bounds}" if bounds else "") + " (e.g. 16,32,64)"

    def parse(text):
        try:
            values = [int(v) for v in str(text).split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not values or any((lo is not None and v < lo) or (hi is not None and v > hi) for v in values):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return values

    parse.__name__ = "int_list"
    return parse


def number_list(*, count: int | None = None, lo=None, lo_open: bool = False):
    """An ``argparse`` type: comma-separated finite numbers (exactly ``count`` of them, if given).

    Examples:
        >>> number_list(count=2, lo=0, lo_open=True)("3,0.4")
        [3.0, 0.4]
        >>> number_list(count=2, lo=0, lo_open=True)("3")
        Traceback (most recent call last):
        ...
        argparse.ArgumentTypeError: expected 2 comma-separated finite numbers > 0, got '3'
    """
    bounds = _bounds(lo, None, lo_open, False)
    expected = (f"{count} " if count else "") + "comma-separated finite numbers" + (f" {bounds}" if bounds else "")
    one = number(lo=lo, lo_open=lo_open)

    def parse(text):
        try:
            values = [one(v) for v in str(text).split(",") if v.strip()]
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not values or (count is not None and len(values) != count):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return values

    parse.__name__ = "number_list"
    return parse


@contextmanager
def one_line_warnings(*, prefix: str = "torchdeform: warning: "):
    """Show every warning raised inside as one line on stderr (no source line), each once."""
    seen = set()

    def show(message, category, *args, **kw):
        text = " ".join(str(message).split())
        if text not in seen:
            seen.add(text)
            print(f"{prefix}{text}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = show
        yield


def _closed_stdout() -> None:
    """After a reader closed stdout (``| head``): point it at /dev/null so the exit flush is quiet."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass


def guarded(prog: str, func, *args, echo: bool = True) -> int:
    r"""Run ``func(*args)`` and return an exit status; a user's problem becomes one line on stderr.

    * ``0`` (or what ``func`` returns): done. A closed stdout (``| head -5``) also ends with 0,
      quietly: what was read was written.
    * ``2``: a :class:`~torchdeform.errors.TorchdeformError` (bad input, divergence ...), an
      ``OSError`` about a path (missing, a folder, unwritable, disk full or over ``ulimit -f``), or
      memory that ran out: one line ``prog: ...``.
    * ``130``: interrupted.
    * ``1``: anything else is a bug: the traceback and a line asking for a report.

    Warnings raised meanwhile are shown as one line each (:func:`one_line_warnings`). With
    ``echo=False`` (ranks other than 0) nothing is printed, only the status returned.

    Examples:
        >>> from torchdeform.errors import ConfigError
        >>> def bad():
        ...     raise ConfigError("--dt", "a positive number (s)", got=-1.0)
        >>> import contextlib, io
        >>> err = io.StringIO()
        >>> with contextlib.redirect_stderr(err):
        ...     status = guarded("torchdeform run", bad)
        >>> status, err.getvalue()
        (2, 'torchdeform run: --dt: expected a positive number (s), got -1.0\n')
    """
    import torch

    from .errors import TorchdeformError

    def say(text: object) -> None:
        if echo:  # one line per problem (several problems of one file: a few lines)
            for line in str(text).splitlines() or [""]:
                if line.strip():
                    print(f"{prog}: {' '.join(line.split())}", file=sys.stderr)

    try:
        with one_line_warnings(prefix=f"{prog}: warning: "):
            status = func(*args)
        try:
            sys.stdout.flush()
        except BrokenPipeError:
            _closed_stdout()
        return 0 if status is None else status
    except TorchdeformError as e:
        say(e)
    except BrokenPipeError:
        _closed_stdout()
        return 0
    except (MemoryError, getattr(torch, "OutOfMemoryError", MemoryError)) as e:
        detail = str(e).split("\n")[0][:200]
        say(
            f"out of memory ({type(e).__name__}{': ' + detail if detail else ''}); a smaller grid, volume, image "
            "or fewer recorded frames would fit"
        )
    except KeyboardInterrupt:
        say("interrupted")
        return 130
    except Exception as e:
        if isinstance(e, OSError) and (e.filename is not None or e.strerror is not None):
            where = f"{e.filename}: " if e.filename is not None else ""
            say(f"{where}{e.strerror or e}")
            return 2
        if echo:
            traceback.print_exc()
        say(REPORT)
        return 1
    return 2

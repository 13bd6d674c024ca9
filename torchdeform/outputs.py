"""Writing outputs so that nothing is lost: whole files, finite values, run folders that hold one run.

* :func:`atomic_path`: write a file under a temporary name beside it and rename it over the
  target only when the write finished, so a failed or interrupted write (a full disk, ``ulimit -f``,
  Ctrl-C) leaves the previous file as it was, never a truncated one.
* :class:`RunFolder`: a run writes every output into a staging folder; when the run ends well the
  files are renamed into the output folder, files listed by the previous run's manifest and not
  written again are removed, and ``summary.json`` lists what the folder now holds
  (``"outputs"``). A run that fails leaves the folder as it was.
* :func:`require_finite`: the guard every writer calls: a NaN or inf in an output is refused
  with the quantity, where it went non-finite and a likely cause.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Literal

import numpy as np

from .errors import ConfigError, TorchdeformError

__all__ = [
    "summary_json",
    "atomic_path",
    "save_figure",
    "axes",
    "figure",
    "save_plot",
    "RunFolder",
    "manifest",
    "require_finite",
    "non_finite_keys",
    "NonFiniteOutputError",
    "OutputError",
    "STAGING",
]

#: prefix of the staging folders and temporary files (hidden; removed when their process is gone)
STAGING = ".torchdeform-partial-"


def _suffixes(path: Path) -> str:
    """The file's suffixes that writers look at (``.nii.gz``, ``.npz``, ``.png``)."""
    name = path.name
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return path.suffix


@contextmanager
def atomic_path(path, *, key: str = "--out"):
    """Yield a temporary path beside ``path`` (same suffix); rename it onto ``path`` on success.

    Writers that choose the format by the suffix (PIL, trimesh, numpy) see the right one. If the
    block raises, the temporary file is removed and ``path`` is untouched.

    Raises:
        ConfigError: ``path`` is a folder, or its folder does not exist or is not a folder.

    Examples:
        >>> import numpy as np
        >>> out = getfixture("tmp_path") / "a.npy"
        >>> np.save(out, np.zeros(3))
        >>> try:
        ...     with atomic_path(out) as tmp:
        ...         np.save(tmp, np.ones(3))
        ...         raise OSError(27, "File too large", str(tmp))
        ... except OSError:
        ...     pass
        >>> np.load(out)                                      # the previous file, whole
        array([0., 0., 0.])
        >>> with atomic_path(out) as tmp:
        ...     np.save(tmp, np.ones(3))
        >>> np.load(out), sorted(p.name for p in out.parent.iterdir())
        (array([1., 1., 1.]), ['a.npy'])
    """
    path = Path(path)
    if path.is_dir():
        raise ConfigError(key, "a file path, not a folder", got=str(path))
    parent = path.parent
    if not parent.is_dir():
        what = "is not a folder" if parent.exists() else "does not exist"
        raise ConfigError(key, f"a path in an existing folder ({parent} {what})", got=str(path))
    suffix = _suffixes(path)
    stem = path.name[: len(path.name) - len(suffix)] if suffix else path.name
    tmp = parent / f"{STAGING}{os.getpid()}-{stem}{suffix}"
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(2, "the writer wrote nothing", str(tmp))
        os.replace(tmp, path)
    except OSError as e:
        if not isinstance(e, TorchdeformError) and (e.filename is None or str(e.filename) == str(tmp)):
            raise OutputError(
                f"{path}: writing failed ({e.strerror or e}); "
                + ("the earlier file is kept" if path.exists() else "nothing was written")
            ) from e
        raise
    finally:
        if tmp.exists():
            tmp.unlink()


def save_figure(fig, path, *, dpi: int = 100) -> None:
    """Write a matplotlib figure to ``path`` (format by suffix) whole or not at all (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)


def axes(*, figsize=(6.5, 4.5), ncols: int = 1):
    """A matplotlib figure and its axes (``ncols`` side by side, ``figsize`` in inches) for a plot; Agg, no screen.

    Examples:
        >>> from torchdeform.outputs import axes
        >>> fig, (left, right) = axes(figsize=(8, 3), ncols=2)
        >>> fig.get_size_inches().tolist()
        [8.0, 3.0]
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(1, ncols, figsize=figsize)


def figure(*, figsize=(6.5, 4.5)):
    """A matplotlib figure of ``figsize`` inches with constrained layout on its own Agg canvas (no pyplot, no screen).

    Examples:
        >>> from torchdeform.outputs import figure
        >>> fig = figure(figsize=(8, 3))
        >>> left, right = fig.subplots(1, 2)
        >>> fig.get_size_inches().tolist(), fig.get_layout_engine() is not None
        ([8.0, 3.0], True)
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_plot(fig, out_dir, name: str) -> None:
    """Write ``fig`` as ``out_dir/name`` (110 dpi, tight layout, atomically), close it and say so on stderr."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(out_dir) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}", file=sys.stderr)


def summary_json(summary: dict, *, series_on_one_line: bool = True) -> str:
    """``summary`` as indented JSON; each series (a list of numbers, or of such lists) on one line.

    Raises :class:`NonFiniteOutputError` naming the keys where a figure is NaN or inf.

    Example:
        >>> print(summary_json({"t": [0.0, 0.5], "force": [[1, 2], [3, 4]]}))
        {
          "t": [0.0, 0.5],
          "force": [[1, 2], [3, 4]]
        }
    """
    try:
        text = json.dumps(summary, indent=2, allow_nan=False)
    except ValueError:
        raise NonFiniteOutputError(
            f"refusing to write summary.json: a figure of the run is NaN or inf ({', '.join(non_finite_keys(summary))})"
        ) from None
    if not series_on_one_line:
        return text
    text = re.sub(r"\[\s+([-+\d.eE,\s]+?)\s+\]", lambda m: "[" + ", ".join(re.split(r",\s*", m.group(1))) + "]", text)
    return re.sub(
        r"\[\s+(\[[^\[\]]*\](?:,\s+\[[^\[\]]*\])*)\s+\]",
        lambda m: "[" + ", ".join(re.split(r"(?<=\]),\s+", m.group(1))) + "]",
        text,
    )


def manifest(folder, *, also=("summary.json",)) -> list:
    """The files under ``folder`` (relative POSIX paths, sorted), plus ``also``: a run's outputs."""
    folder = Path(folder)
    names = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}
    return sorted(names | set(also))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _remove_orphans(folder: Path) -> None:
    """Staging folders and temporary files left by processes that are gone (a killed run)."""
    for p in folder.glob(STAGING + "*"):
        pid = p.name[len(STAGING) :].split("-")[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


def _previous(folder: Path) -> list | None:
    """The previous run's manifest (``summary.json`` ``"outputs"``), or None if there is none."""
    try:
        listed = json.loads((folder / "summary.json").read_text()).get("outputs")
    except (OSError, ValueError, AttributeError):
        return None
    return [str(n) for n in listed] if isinstance(listed, list) else None


class RunFolder:
    """An output folder that holds exactly the outputs of its last run.

    Use as a context manager: the block writes its outputs into the staging folder it is given;
    when the block ends without an exception, :meth:`commit` moves them in. The run's
    ``summary.json`` should list them: write it last with ``manifest(stage)`` as ``"outputs"``.

    Args:
        out: the output folder (created if needed).
        force: write into a folder that holds other files and no earlier run's ``summary.json``
            (they are left alone); without it such a folder is refused, so that ``--out .`` does not
            mix a run's outputs with unrelated files.
        key: the option or parameter named in errors.

    Raises:
        ConfigError: ``out`` is a file, cannot be created, or holds unrelated files (without ``force``).

    Examples:
        >>> import json
        >>> out = getfixture("tmp_path") / "run"
        >>> with RunFolder(out) as stage:                      # a first run writes a and b
        ...     _ = (stage / "a.txt").write_text("1")
        ...     _ = (stage / "b.txt").write_text("1")
        ...     _ = (stage / "summary.json").write_text(json.dumps({"outputs": manifest(stage)}))
        >>> with RunFolder(out) as stage:                      # a second run writes only a
        ...     _ = (stage / "a.txt").write_text("2")
        ...     _ = (stage / "summary.json").write_text(json.dumps({"outputs": manifest(stage)}))
        >>> sorted(p.name for p in out.iterdir()), (out / "a.txt").read_text()
        (['a.txt', 'summary.json'], '2')
        >>> try:
        ...     with RunFolder(out) as stage:                  # a failed run changes nothing
        ...         _ = (stage / "a.txt").write_text("3")
        ...         raise OSError(27, "File too large")
        ... except OSError:
        ...     pass
        >>> sorted(p.name for p in out.iterdir()), (out / "a.txt").read_text()
        (['a.txt', 'summary.json'], '2')
    """

    def __init__(self, out, *, force: bool = False, key: str = "--out"):
        self.out, self.force, self.key = Path(out), force, key
        self.stage = None

    def check(self) -> None:
        """Refuse an unusable ``out`` before any work (creates nothing; also safe on every rank)."""
        out = self.out
        if out.exists() and not out.is_dir():
            raise ConfigError(self.key, "a folder (this path is a file)", got=str(out))
        parent = out
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir():
            raise ConfigError(self.key, f"a folder that can be created ({parent} is a file)", got=str(out))
        if not os.access(parent, os.W_OK | os.X_OK):
            raise ConfigError(self.key, f"a folder this user can write to ({parent} is not writable)", got=str(out))
        if out.is_dir() and not self.force and _previous(out) is None:
            others = sorted(p.name for p in out.iterdir() if not p.name.startswith(STAGING))
            if others:
                shown = ", ".join(others[:3]) + (", ..." if len(others) > 3 else "")
                raise ConfigError(
                    self.key,
                    f"an empty folder or the folder of an earlier run (one with summary.json); "
                    f"it holds {len(others)} other entries ({shown}): choose another folder or add "
                    "--force to write beside them",
                    got=str(out),
                )

    def __enter__(self) -> Path:
        self.check()
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ConfigError(self.key, f"a folder that can be created ({e.strerror})", got=str(self.out)) from None
        _remove_orphans(self.out)
        self.previous = _previous(self.out)
        self.stage = self.out / f"{STAGING}{os.getpid()}"
        shutil.rmtree(self.stage, ignore_errors=True)
        self.stage.mkdir()
        return self.stage

    def __exit__(self, kind, value, tb) -> Literal[False]:
        assert self.stage is not None  # set by __enter__
        try:
            if kind is None:
                self.commit()
        finally:
            shutil.rmtree(self.stage, ignore_errors=True)
        if isinstance(value, OSError) and not isinstance(value, TorchdeformError) and value.filename is None:
            raise OutputError(
                f"{self.out}: writing the outputs failed ({value.strerror or value}); the folder keeps "
                "what it held before"
            ) from value
        return False

    def commit(self) -> list:
        """Move the staged files in (``summary.json`` last) and remove the previous run's leftovers."""
        written = manifest(self.stage, also=())
        for name in sorted(written, key=lambda n: n == "summary.json"):
            target = self.out / name
            if target.is_dir():
                shutil.rmtree(target)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(self.stage / name, target)
        for name in set(self.previous or ()) - set(written):
            target = self.out / name
            if ".." not in Path(name).parts and target.is_file():
                target.unlink()
                parent = target.parent
                while parent != self.out and parent.is_dir() and not any(parent.iterdir()):
                    parent.rmdir()
                    parent = parent.parent
        return written


class OutputError(TorchdeformError, OSError):
    """Outputs could not be written (a full disk, ``ulimit -f``); earlier outputs are kept."""


class NonFiniteOutputError(TorchdeformError, FloatingPointError):
    """An output would have held NaN or inf: it was not written."""


def require_finite(name: str, value, *, what: str = "", cause: str = "") -> None:
    """Refuse an output holding NaN or inf: raise :class:`NonFiniteOutputError` naming it and where.

    Args:
        name: the output quantity, e.g. ``"trajectory.npz: x"``.
        value: a tensor, array or number.
        what: how an index reads, e.g. ``"frame, axis, d, h, w"`` (the first bad entry is shown).
        cause: a likely cause, added to the message.

    Examples:
        >>> import numpy as np
        >>> require_finite("series.npz: x", np.zeros((2, 3)))
        >>> require_finite("series.npz: x", np.array([[0, 1], [np.nan, 2]]), what="step, node", cause="--amplitude is nan")
        Traceback (most recent call last):
        ...
        torchdeform.outputs.NonFiniteOutputError: refusing to write series.npz: x is nan at step, node (1, 0) ...
    """
    arr = value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)
    if arr.dtype.kind not in "fc":
        return
    bad = ~np.isfinite(arr)
    if not bad.any():
        return
    first = tuple(int(i) for i in np.argwhere(bad)[0]) if arr.ndim else ()
    at = f" at {what or 'index'} {first}" if first else ""
    reason = f"; {cause}" if cause else ""
    raise NonFiniteOutputError(
        f"refusing to write {name} is {arr[first] if first else arr.item()}{at} "
        f"({int(bad.sum())} of {arr.size} values are not finite){reason}"
    )


def non_finite_keys(tree, *, path: str = "", limit: int = 5) -> list:
    """The dotted keys of the NaN or inf numbers in a JSON-like tree (at most ``limit``).

    Examples:
        >>> non_finite_keys({"a": 1.0, "b": [0.0, float("nan")], "c": {"d": float("inf")}})
        ['b[1] = nan', 'c.d = inf']
    """
    found = []
    if isinstance(tree, dict):
        for k, v in tree.items():
            found += non_finite_keys(v, path=f"{path}.{k}" if path else str(k), limit=limit)
    elif isinstance(tree, (list, tuple)):
        for i, v in enumerate(tree):
            found += non_finite_keys(v, path=f"{path}[{i}]", limit=limit)
    elif isinstance(tree, float) and not math.isfinite(tree):
        found.append(f"{path} = {tree}")
    return found[:limit]

"""Checks at the boundary, before work starts: a device that works, and memory that suffices.

* :func:`usable_device`: a device name torch accepts is not always one it can use (``meta`` holds
  no values, ``xpu`` or ``cuda`` may be missing from this build): try it once and say what is
  missing.
* :func:`read_text`: an input text file (scene, rule file, CSV, transfer function) as UTF-8, or one
  located line saying what is wrong (missing, a folder, not UTF-8 at line n).
* :func:`check_memory`: refuse a grid, volume, image or recording that cannot fit, naming the key
  and the bytes it would take, instead of failing inside an allocation.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import torch

from .errors import ConfigError

__all__ = ["usable_device", "read_text", "available_memory", "check_memory", "check_grid", "format_bytes"]


@functools.lru_cache(maxsize=16)
def _try_device(name: str) -> str | None:
    """None if a small computation on device ``name`` works and comes back, else why not."""
    try:
        dev = torch.device(name)
        if dev.type == "meta":
            return "meta tensors hold no values"
        if dev.type == "cuda" and not torch.cuda.is_available():
            return "this torch sees no CUDA device (torch.cuda.is_available() is False)"
        if dev.type == "cuda" and (dev.index or 0) >= torch.cuda.device_count():
            return f"this machine has {torch.cuda.device_count()} CUDA device(s)"
        x = torch.arange(4.0, device=dev)
        if float((x * 2).sum().cpu()) != 12.0:
            return "a test sum came back wrong"
    except Exception as e:  # whatever the backend raises: it cannot be used here
        text = " ".join(str(e).split()) or type(e).__name__
        return text[:160]
    return None


def usable_device(device, *, key: str = "--device", file=None, line=None) -> torch.device:
    """``device`` as a :class:`torch.device` that works here, or a :class:`ConfigError` saying why not.

    Args:
        device: a name (``"cpu"``, ``"cuda"``, ``"cuda:1"``) or a :class:`torch.device`; None = CPU.
        key: the option or scene key named in the error.
        file: the scene file, when the device came from one.
        line: its line.

    Examples:
        >>> usable_device("cpu")
        device(type='cpu')
        >>> usable_device("meta", key="integrator.device")
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: integrator.device: expected a device this torch can compute on ("cpu"...
        >>> usable_device("abc")
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: --device: expected a device name such as "cpu", "cuda" or "cuda:1", got 'abc'
    """
    if device is None:
        return torch.device("cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ConfigError(
            key, 'a device name such as "cpu", "cuda" or "cuda:1"', got=device, file=file, line=line
        ) from None
    why = _try_device(str(dev))
    if why is not None:
        raise ConfigError(
            key, f'a device this torch can compute on ("cpu"{_others()}); {dev}: {why}', file=file, line=line
        )
    return dev


def _others() -> str:
    n = torch.cuda.device_count() if torch.cuda.is_available() else 0
    return "" if n == 0 else (', "cuda"' if n == 1 else f', "cuda:0" ... "cuda:{n - 1}"')


def format_bytes(n: float) -> str:
    """``1.5 GiB`` style.

    Examples:
        >>> format_bytes(3 * 2**30), format_bytes(512)
        ('3 GiB', '512 B')
    """
    for unit, size in (("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} B"


def available_memory(*, device=None) -> int | None:
    """Bytes that can still be allocated on ``device`` (CPU: ``MemAvailable``), or None if unknown."""
    dev = torch.device(device or "cpu")
    if dev.type == "cuda":
        try:
            return int(torch.cuda.mem_get_info(dev)[0])
        except Exception:
            return None
    if dev.type != "cpu":
        return None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(key: str, nbytes: float, what: str, *, device=None, got=None, file=None, line=None) -> None:
    """Refuse (``ConfigError`` naming ``key``) when ``nbytes`` exceed what ``device`` has available.

    Args:
        key: the scene key or option that sets the size (``"grid.shape"``, ``"--size"``).
        nbytes: an estimate of what the work needs (a lower bound: refusals are certain).
        what: the thing, e.g. ``"a grid of 2000 x 2000 x 2000 nodes"``.
        device: where it would live (None = CPU).
        got: the value shown in the error.
        file: the scene file, when the size came from one.
        line: its line.

    Examples:
        >>> check_memory("grid.shape", 1e3, "a grid of 4 x 4 x 4 nodes")
        >>> check_memory("grid.shape", 1e18, "a grid of 1e6 x 1e6 x 1e6 nodes", got=[10**6] * 3)
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: grid.shape: expected a size that fits in memory: a grid of 1e6 x 1e6 x 1e6 nodes needs at least 888 PiB...
    """
    avail = available_memory(device=device)
    if avail is None or nbytes <= avail:
        return
    raise ConfigError(
        key,
        f"a size that fits in memory: {what} needs at least {format_bytes(nbytes)}, and "
        f"{format_bytes(avail)} is available on {torch.device(device or 'cpu')}",
        got=got,
        file=file,
        line=line,
    )


def read_text(path, key: str, *, what: str = "file") -> str:
    r"""The UTF-8 text of an input file, or a :class:`ConfigError` naming ``key`` (and the line of a bad byte).

    Args:
        path: the file.
        key: the option or key that named it (``"--inputs"``, ``"scene"``).
        what: what the file should be, e.g. ``"CSV file"``.

    Examples:
        >>> p = getfixture("tmp_path") / "bad.csv"
        >>> _ = p.write_bytes(b"a,b\n1,2\n\xff,3\n")
        >>> read_text(p, "--inputs", what="CSV file")
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: ...bad.csv:3: --inputs: expected a UTF-8 text CSV file, got 'byte 0xff that is not UTF-8'
        >>> read_text(p.parent, "--inputs", what="CSV file")
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: --inputs: expected a CSV file, not a folder, got '...'
    """
    p = Path(path)
    if p.is_dir():
        raise ConfigError(key, f"a {what}, not a folder", got=str(p))
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise ConfigError(key, f"an existing {what}", got=str(p)) from None
    except OSError as e:
        raise ConfigError(key, f"a readable {what} ({e.strerror})", got=str(p)) from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise ConfigError(
            key,
            f"a UTF-8 text {what}",
            got=f"byte 0x{data[e.start]:02x} that is not UTF-8",
            file=str(p),
            line=line,
            show_got=True,
        ) from None


def check_grid(key: str, shape, *, topology: int = 26, itemsize: int = 4, device=None, file=None, line=None) -> None:
    """Refuse a node grid whose model cannot fit in memory (:func:`check_memory`).

    The estimate (a lower bound): state, rest positions, masses, forces and the integrator's
    work fields (about 30 values per node), and the spring fields (``topology`` per node).

    Args:
        key: the scene key or option of the size.
        shape: the node counts ``(D, H, W)``.
        topology: neighbours per node.
        itemsize: bytes per value (4: float32).
        device: where the model would live (None = CPU).
        file: the scene file, if any.
        line: its line.

    Examples:
        >>> check_grid("grid.shape", (64, 64, 64))
        >>> check_grid("grid.shape", (100000, 100000, 100000))
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: grid.shape: expected a size that fits in memory: a grid of 100000 x 100000 x 100000 nodes...
    """
    nodes = 1
    for n in shape:
        nodes *= int(n)
    check_memory(
        key,
        float(nodes) * itemsize * (30 + int(topology)),
        f"a grid of {' x '.join(str(int(n)) for n in shape)} nodes ({topology} neighbours)",
        device=device,
        got=list(shape),
        file=file,
        line=line,
    )

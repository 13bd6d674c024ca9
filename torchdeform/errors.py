"""The one error hierarchy of torchdeform.

Every problem a user can cause ends in one of these, with one sentence that names what was
wrong (file, key, parameter, node or step) and what was expected.
"""

from __future__ import annotations

import math

__all__ = [
    "TorchdeformError",
    "ConfigError",
    "DivergenceError",
    "NoRuleFiredError",
    "StabilityWarning",
    "ConfigWarning",
    "positive_number",
]


class TorchdeformError(Exception):
    """Base class of every error torchdeform raises on purpose.

    Examples:
        >>> import torchdeform as td
        >>> try:
        ...     td.Grid((0, 4, 4), spacing=0.01)
        ... except td.TorchdeformError as e:
        ...     print(type(e).__name__, "-", e)
        ConfigError - grid.shape: expected three node counts D, H, W, each >= 1, got (0, 4, 4)
        >>> issubclass(td.DivergenceError, td.TorchdeformError)
        True
    """


class ConfigError(TorchdeformError, ValueError):
    """A bad parameter or scene entry.

    Args:
        key: the parameter or scene key, e.g. ``"material.stiffness"``.
        expected: what would have been accepted, e.g. ``"a positive number"``.
        got: the offending value (shown with ``repr``), optional.
        file: the scene file, optional.
        line: line number in ``file``, optional.
        show_got: show ``got`` in the message (when it is not None).

    Examples:
        >>> import torchdeform as td
        >>> e = td.ConfigError("material.stiffness", "a number >= 0 (N/m)", got=-3.0, file="cube.toml", line=7)
        >>> str(e)
        'cube.toml:7: material.stiffness: expected a number >= 0 (N/m), got -3.0'
        >>> e.key, e.line, isinstance(e, ValueError)
        ('material.stiffness', 7, True)
    """

    def __init__(self, key: str, expected: str, *, got=None, file=None, line=None, show_got=True):
        self.key, self.expected, self.got, self.file, self.line = key, expected, got, file, line
        self.show_got = show_got and got is not None
        where = ""
        if file is not None:
            where = f"{file}:{line}: " if line is not None else f"{file}: "
        tail = f", got {got!r}" if self.show_got else ""
        super().__init__(f"{where}{key}: expected {expected}{tail}")


class DivergenceError(TorchdeformError, FloatingPointError):
    """A run became unstable: non-finite values or runaway energy.

    Attributes:
        step: the step index at which it was detected.
        quantity: what went wrong (``"position"``, ``"velocity"``, ``"kinetic energy"`` ...).
        value: the offending value (may be ``nan`` or ``inf``).
        dt: the time step in use.
        safe_dt: a time step that the stability bound allows, or None.
        cause: the likely cause when it is not the time step (shown instead of the safe dt), or None.

    Examples:
        >>> import torchdeform as td
        >>> e = td.DivergenceError(120, "velocity", float("inf"), dt=1e-3, safe_dt=2e-4)
        >>> str(e).split(";")[0]
        'simulation diverged at step 120: velocity is inf with dt = 0.001 s'
        >>> e.safe_dt, isinstance(e, FloatingPointError)
        (0.0002, True)
    """

    def __init__(
        self, step: int, quantity: str, value: float, dt: float, safe_dt: float | None, *, cause: str | None = None
    ):
        self.step, self.quantity, self.value, self.dt, self.safe_dt = step, quantity, value, dt, safe_dt
        self.cause = cause
        hint = f"; a safe time step for this model is about {safe_dt:.3g} s" if safe_dt else ""
        if cause:
            hint = f"; {cause}"
        super().__init__(f"simulation diverged at step {step}: {quantity} is {value:.3g} with dt = {dt:.3g} s{hint}")


class NoRuleFiredError(TorchdeformError, ValueError):
    """A fuzzy system asked to raise (``on_empty="error"``) found input rows where no rule fires."""


class StabilityWarning(UserWarning):
    """A requested explicit time step exceeds the model's stability bound.

    Examples:
        >>> import warnings
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3)
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     bound = td.check_dt(model, 1.0, "symplectic")          # 1 s: far above the bound
        >>> caught[0].category is td.StabilityWarning, issubclass(td.StabilityWarning, UserWarning)
        (True, True)
    """


class ConfigWarning(UserWarning):
    """A legal value that is probably not what was meant (a unit mixed up, an old key name).

    Examples:
        >>> import warnings
        >>> import torchdeform as td
        >>> with warnings.catch_warnings(record=True) as w:
        ...     warnings.simplefilter("always")
        ...     warnings.warn("material.modulus: renamed spring_modulus", td.ConfigWarning, stacklevel=1)
        >>> w[0].category.__name__
        'ConfigWarning'
    """


def positive_number(value, key: str, *, expected: str = "a positive number") -> float:
    """``value`` as a positive, finite float, or a :class:`ConfigError` naming ``key``.

    Examples:
        >>> positive_number("0.5", "radius")
        0.5
        >>> positive_number(-1, "radius", expected="a positive number of metres")
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: radius: expected a positive number of metres, got -1
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(key, expected, got=value) from None
    if not math.isfinite(v) or v <= 0:
        raise ConfigError(key, expected, got=value)
    return v

"""The one error hierarchy of torchdeform.

Every problem a user can cause ends in one of these, with one sentence that names what was
wrong (file, key, parameter, node or step) and what was expected.
"""
from __future__ import annotations


class TorchdeformError(Exception):
    """Base class of every error torchdeform raises on purpose."""


class ConfigError(TorchdeformError, ValueError):
    """A bad parameter or scene entry.

    Args:
        key: the parameter or scene key, e.g. ``"material.stiffness"``.
        expected: what would have been accepted, e.g. ``"a positive number"``.
        got: the offending value (shown with ``repr``), optional.
        file: the scene file, optional.
        line: line number in ``file``, optional.
    """

    def __init__(self, key: str, expected: str, got=None, file=None, line=None, *, show_got=True):
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
        dt: the time step in use; ``safe_dt``: a time step that the stability bound allows.
    """

    def __init__(self, step: int, quantity: str, value: float, dt: float, safe_dt: float | None):
        self.step, self.quantity, self.value, self.dt, self.safe_dt = step, quantity, value, dt, safe_dt
        hint = f"; a safe time step for this model is about {safe_dt:.3g} s" if safe_dt else ""
        super().__init__(
            f"simulation diverged at step {step}: {quantity} is {value:.3g} with dt = {dt:.3g} s{hint}"
        )


class NoRuleFiredError(TorchdeformError, ValueError):
    """A fuzzy system asked to raise (``on_empty="error"``) found input rows where no rule fires."""


class StabilityWarning(UserWarning):
    """A requested explicit time step exceeds the model's stability bound."""

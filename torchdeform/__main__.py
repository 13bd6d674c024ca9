"""``python -m torchdeform``: the ``torchdeform`` command (:func:`torchdeform.cli.main`)."""

from .cli import entry

__all__: list = []

entry()

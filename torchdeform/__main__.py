"""``python -m torchdeform``: the ``torchdeform`` command (:func:`torchdeform.cli.main`)."""

import sys

from .cli import main

__all__: list = []

sys.exit(main())

"""Data package ``torchdeform.rulefiles``: the shipped fuzzy rule files (``*.fis``) and the tissue
library (``tissues.toml``). No code is imported from here; load the files with
:mod:`torchdeform.fuzzy.presets`. ``reconstruct.py`` regenerates the ``.fis`` files."""

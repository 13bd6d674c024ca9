"""Mamdani fuzzy systems: linguistic tissue terms to stiffness and viscosity.

    >>> from torchdeform import fuzzy
    >>> fis = fuzzy.load_preset("susilap_g")          # Radetzky's SUSILAP-G (reconstructed MFs)
    >>> out = fis.evaluate(consistency=5.5)
    >>> round(float(out["spring_const"]), 2), round(float(out["viscosity"]), 3)
    (16.26, 2.877)

Modules: :mod:`.membership` (membership functions, hedges), :mod:`.rules` (variables,
rule sentences), :mod:`.system` (inference, defuzzification), :mod:`.fis` (MATLAB ``.fis``
files), :mod:`.presets` (the shipped rule files), :mod:`.coupling` (per-node and per-region
inputs to per-spring stiffness and damping).
"""

from .membership import (
    HEDGES,
    KINDS,
    Bell,
    Binary,
    Concave,
    Cosine,
    DiffSigmoid,
    Discrete,
    Gaussian,
    Gaussian2,
    LinS,
    LinZ,
    MembershipFunction,
    PiShape,
    ProdSigmoid,
    Ramp,
    Rectangle,
    Sigmoid,
    Singleton,
    Spike,
    SShape,
    Trapezoid,
    Triangle,
    ZShape,
)
from .presets import list_presets, load_preset, tissue_parameters, tissues
from .rules import Clause, Rule, Variable
from .system import (
    AGGREGATIONS,
    AND_METHODS,
    DEFUZZIFIERS,
    IMPLICATIONS,
    OR_METHODS,
    EmptyOutputWarning,
    MamdaniSystem,
    ResolutionWarning,
    defuzzify,
)

__all__ = [
    "HEDGES",
    "KINDS",
    "Bell",
    "Gaussian",
    "MembershipFunction",
    "Sigmoid",
    "Singleton",
    "Trapezoid",
    "Triangle",
    "ZShape",
    "SShape",
    "PiShape",
    "DiffSigmoid",
    "ProdSigmoid",
    "Gaussian2",
    "LinS",
    "LinZ",
    "Ramp",
    "Rectangle",
    "Concave",
    "Cosine",
    "Spike",
    "Binary",
    "Discrete",
    "Clause",
    "Rule",
    "Variable",
    "AGGREGATIONS",
    "AND_METHODS",
    "DEFUZZIFIERS",
    "IMPLICATIONS",
    "OR_METHODS",
    "EmptyOutputWarning",
    "ResolutionWarning",
    "MamdaniSystem",
    "defuzzify",
    "list_presets",
    "load_preset",
    "tissue_parameters",
    "tissues",
]

"""Mamdani fuzzy systems: linguistic tissue terms to stiffness and viscosity.

    >>> from torchdeform.fuzzy.fis import read_fis
    >>> fis = read_fis("tests/data/fis/tipper.fis")
    >>> fis.evaluate(service=1.0, food=2.0)            # {'tip': tensor(5.5539)}

Modules: :mod:`.membership` (membership functions, hedges), :mod:`.rules` (variables,
rule sentences), :mod:`.system` (inference, defuzzification), :mod:`.fis` (MATLAB ``.fis``
files), :mod:`.coupling` (per-node and per-region
inputs to per-spring stiffness and damping).
"""
from .membership import HEDGES, KINDS, Bell, Gaussian, MembershipFunction, Sigmoid, Singleton, Trapezoid, Triangle
from .rules import Clause, Rule, Variable
from .system import (AGGREGATIONS, AND_METHODS, DEFUZZIFIERS, IMPLICATIONS, OR_METHODS, EmptyOutputWarning,
                     MamdaniSystem, defuzzify)

__all__ = ["HEDGES", "KINDS", "Bell", "Gaussian", "MembershipFunction", "Sigmoid", "Singleton", "Trapezoid",
           "Triangle", "Clause", "Rule", "Variable", "AGGREGATIONS", "AND_METHODS", "DEFUZZIFIERS",
           "IMPLICATIONS", "OR_METHODS", "EmptyOutputWarning", "MamdaniSystem", "defuzzify"]

"""What the engine reads and computes, against MATLAB, Octave, scikit-fuzzy and fuzzylite: one table.

:data:`VOCABULARY` lists every membership kind, hedge, operator and defuzzifier of
:mod:`torchdeform.fuzzy` with its name in each peer (``-`` where the peer has none); the
``torchdeform fuzzy vocabulary`` command prints it (:func:`vocabulary_table`) and draws every
membership kind (:func:`plot_kinds`), and the fuzzy guide holds the same table.

Example:
    >>> from torchdeform.fuzzy.vocabulary import VOCABULARY, vocabulary_table
    >>> [row for row in VOCABULARY if row[1] == "zshape"]
    [('membership', 'zshape', 'zmf', 'zmf', 'zmf', 'ZShape')]
    >>> vocabulary_table().splitlines()[0]
    '| kind | torchdeform | MATLAB | Octave | scikit-fuzzy | fuzzylite |'
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from ..outputs import save_figure
from .membership import KINDS

__all__ = ["VOCABULARY", "EXAMPLE_PARAMETERS", "vocabulary_table", "plot_kinds"]

#: (kind of word, our name, MATLAB's, Octave's fuzzy-logic-toolkit's, scikit-fuzzy's, fuzzylite's).
#: Membership kinds by their ``.fis`` type (fuzzylite: its term class; its ``.fis`` names are
#: ``rampmf`` ... in :mod:`~torchdeform.fuzzy.fis`); hedges by rule code where the peer encodes
#: them in ``.fis`` rules; operators by ``.fis`` method name (fuzzylite: its norm class).
VOCABULARY = [
    ("membership", "trapezoid", "trapmf", "trapmf", "trapmf", "Trapezoid"),
    ("membership", "triangle", "trimf", "trimf", "trimf", "Triangle"),
    ("membership", "gaussian", "gaussmf", "gaussmf", "gaussmf", "Gaussian"),
    ("membership", "bell", "gbellmf", "gbellmf", "gbellmf", "Bell"),
    ("membership", "sigmoid", "sigmf", "sigmf", "sigmf", "Sigmoid"),
    ("membership", "zshape", "zmf", "zmf", "zmf", "ZShape"),
    ("membership", "sshape", "smf", "smf", "smf", "SShape"),
    ("membership", "pishape", "pimf", "pimf", "pimf", "PiShape"),
    ("membership", "dsigmoid", "dsigmf", "dsigmf", "dsigmf (signed)", "SigmoidDifference"),
    ("membership", "psigmoid", "psigmf", "psigmf", "psigmf", "SigmoidProduct"),
    ("membership", "gaussian2", "gauss2mf", "gauss2mf", "gauss2mf", "GaussianProduct"),
    ("membership", "lins", "linsmf", "linsmf", "-", "-"),
    ("membership", "linz", "linzmf", "linzmf", "-", "-"),
    ("membership", "ramp", "-", "-", "-", "Ramp"),
    ("membership", "rectangle", "-", "-", "-", "Rectangle"),
    ("membership", "concave", "-", "-", "-", "Concave"),
    ("membership", "cosine", "-", "-", "-", "Cosine"),
    ("membership", "spike", "-", "-", "-", "Spike"),
    ("membership", "binary", "-", "-", "-", "Binary"),
    ("membership", "discrete", "-", "-", "-", "Discrete"),
    ("membership", "singleton", "-", "-", "-", "-"),
    ("hedge", "not", "negative index", "negative index", "fuzzy_not", "not"),
    ("hedge", "somewhat", "-", ".05", "-", "somewhat (.05)"),
    ("hedge", "very", "-", ".2", "-", "very (.2)"),
    ("hedge", "cubed", "-", ".3 (mu^3)", "-", "-"),
    ("hedge", "very very", "-", ".4", "-", "very very (.4)"),
    ("hedge", "extremely", "-", "-", "-", "extremely (.3)"),
    ("hedge", "seldom", "-", "-", "-", "seldom (.01)"),
    ("hedge", "any", "-", "-", "-", "any (.99)"),
    ("AND, implication", "min", "min", "min", "np.fmin", "Minimum"),
    ("AND, implication", "prod", "prod", "prod", "np.multiply", "AlgebraicProduct"),
    ("AND, implication", "algebraic_product", "-", "algebraic_product", "-", "AlgebraicProduct"),
    ("AND, implication", "bounded_difference", "-", "bounded_difference", "-", "BoundedDifference"),
    ("AND, implication", "drastic_product", "-", "drastic_product", "-", "DrasticProduct"),
    ("AND, implication", "einstein_product", "-", "einstein_product", "-", "EinsteinProduct"),
    ("AND, implication", "hamacher_product", "-", "hamacher_product", "-", "HamacherProduct"),
    ("OR, aggregation", "max", "max", "max", "np.fmax", "Maximum"),
    ("OR, aggregation", "probor", "probor", "probor", "-", "AlgebraicSum"),
    ("OR, aggregation", "algebraic_sum", "-", "algebraic_sum", "-", "AlgebraicSum"),
    ("OR, aggregation", "bounded_sum", "-", "bounded_sum", "-", "BoundedSum"),
    ("OR, aggregation", "drastic_sum", "-", "drastic_sum", "-", "DrasticSum"),
    ("OR, aggregation", "einstein_sum", "-", "einstein_sum", "-", "EinsteinSum"),
    ("OR, aggregation", "hamacher_sum", "-", "hamacher_sum", "-", "HamacherSum"),
    ("aggregation", "sum", "sum", "sum", "-", "UnboundedSum"),
    ("defuzzification", "centroid", "centroid", "centroid", "centroid", "Centroid"),
    ("defuzzification", "bisector", "bisector", "bisector", "bisector", "Bisector"),
    ("defuzzification", "mom", "mom", "mom", "mom", "MeanOfMaximum"),
    ("defuzzification", "som", "som", "som", "som", "SmallestOfMaximum"),
    ("defuzzification", "lom", "lom", "lom", "lom", "LargestOfMaximum"),
    ("not read (Sugeno)", "-", "wtaver, wtsum", "wtaver, wtsum", "-", "WeightedAverage, WeightedSum"),
]

#: kind -> parameters (our order) drawn by :func:`plot_kinds`, on the axis 0..10
EXAMPLE_PARAMETERS = {
    "trapezoid": (1, 3, 6, 9),
    "triangle": (2, 5, 8),
    "gaussian": (5, 1.5),
    "bell": (2, 3, 5),
    "sigmoid": (5, 2),
    "zshape": (3, 7),
    "sshape": (3, 7),
    "pishape": (1, 4, 6, 9),
    "dsigmoid": (5, 2, 5, 7),
    "psigmoid": (2, 3, -5, 8),
    "gaussian2": (1, 4, 2, 6),
    "lins": (3, 7),
    "linz": (3, 7),
    "ramp": (2, 8),
    "rectangle": (3, 7),
    "concave": (4, 8),
    "cosine": (5, 6),
    "spike": (5, 4),
    "binary": (5, 6),
    "discrete": (0, 0, 2, 0.6, 4, 0.2, 6, 1, 8, 0.4, 10, 0),
    "singleton": (5,),
}


def vocabulary_table() -> str:
    """:data:`VOCABULARY` as a Markdown table (one row per word)."""
    head = ("kind", "torchdeform", "MATLAB", "Octave", "scikit-fuzzy", "fuzzylite")
    rows = [head, ("---",) * len(head)] + [
        tuple(f"`{c}`" if k == 1 and c != "-" else c for k, c in enumerate(r)) for r in VOCABULARY
    ]
    return "\n".join("| " + " | ".join(r) + " |" for r in rows)


def plot_kinds(path, *, points: int = 801) -> Path:
    """Draw every membership kind of :data:`~torchdeform.fuzzy.membership.KINDS` (one panel each) as a PNG.

    Parameters from :data:`EXAMPLE_PARAMETERS`; each panel is titled with the kind and its
    MATLAB or fuzzylite name. Returns the path written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    names = {row[1]: row[2] if row[2] != "-" else row[5] for row in VOCABULARY if row[0] == "membership"}
    kinds = list(KINDS)
    cols = 4
    rows = math.ceil(len(kinds) / cols)
    fig = Figure(figsize=(3.0 * cols, 1.9 * rows))
    FigureCanvasAgg(fig)
    x = torch.linspace(0.0, 10.0, points, dtype=torch.float64)
    for k, kind in enumerate(kinds):
        ax = fig.add_subplot(rows, cols, k + 1)
        mf = KINDS[kind](*EXAMPLE_PARAMETERS[kind])
        with torch.no_grad():
            if mf.is_singleton:
                ax.vlines(mf.values()[0], 0, 1)
            else:
                ax.plot(x.numpy(), mf.double()(x).numpy())
        other = names.get(kind, "-")
        ax.set_title(kind + (f" ({other})" if other != "-" else ""), fontsize=9)
        ax.set_ylim(-0.05, 1.08)
        ax.set_xlim(0, 10)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    return Path(path)

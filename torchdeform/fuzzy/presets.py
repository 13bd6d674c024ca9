"""The shipped rule files: Radetzky's rule bases and an SI tissue library.

==========================  =====================================================================
preset                      contents
==========================  =====================================================================
``susilap_g``               SUSILAP-G (thesis Table C.1): consistency -> spring_const, viscosity
``robo_sim_ventricle``      ROBO-SIM ventricle (Table C.2): consistency, sensitiveness,
                            shiftability -> spring_const, viscosity
``tissue_si``               consistency (0..10) -> youngs_modulus (Pa), viscosity (Pa*s)
==========================  =====================================================================

The rule tables of the two Radetzky presets are as published; their membership functions are
**reconstructions** (the thesis figures that drew them are lost): trapezoids fitted by
torchdeform so that the published input/output pairs come out to better than 1e-4 relative.
Each file's header says so and lists the pairs; ``fuzzy/reconstruct.py`` regenerates them.
Units of the Radetzky outputs are not given in the source.

The files live in the repository's top-level ``fuzzy/`` folder, installed as the data package
``torchdeform.rulefiles`` (:data:`PRESET_DIR`). ``fuzzy/tissues.toml`` lists tissues with
their consistency value on the ``tissue_si`` scale, literature Young's-modulus range, density,
Poisson ratio and sources.

Example:
    >>> from torchdeform.fuzzy import load_preset, tissue_parameters
    >>> fis = load_preset("susilap_g")
    >>> round(float(fis.evaluate(consistency=5.5)["spring_const"]), 2)     # published 16.2606 (Fallopian tube)
    16.26
    >>> liver = tissue_parameters("liver")
    >>> liver["term"], liver["youngs_modulus_range"]                       # Pa
    ('soft', (500.0, 10000.0))
    >>> 500.0 <= liver["youngs_modulus"] <= 10000.0
    True
    >>> liver["poisson_ratio"]                                              # nearly incompressible
    0.49
"""

from __future__ import annotations

import copy
import functools
from pathlib import Path
from typing import TYPE_CHECKING, cast

import torch

from ..errors import ConfigError
from .fis import parse_fis
from .system import MamdaniSystem

if TYPE_CHECKING:
    from .membership import MembershipFunction
    from .rules import Variable

__all__ = [
    "PRESET_DIR",
    "TISSUE_FILE",
    "list_presets",
    "preset_path",
    "load_preset",
    "tissues",
    "tissue_parameters",
    "tissue_properties",
    "tissue_expected",
    "tissue_moduli",
    "TISSUE_EXPECTED",
    "DEFAULT_POISSON_RATIO",
]

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib


def _preset_dir():
    """The folder of the rule files.

    The installed data package ``torchdeform.rulefiles``, or the checkout's ``fuzzy/`` folder when
    torchdeform runs from a source tree that is not installed.
    """
    try:
        from importlib.resources import files

        return files("torchdeform.rulefiles")
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "fuzzy"


#: Where the rule files are (a :class:`pathlib.Path` or an ``importlib.resources`` Traversable).
PRESET_DIR = _preset_dir()

TISSUE_FILE = "tissues.toml"


def list_presets() -> list:
    """Names of the shipped ``.fis`` presets, sorted (``["robo_sim_ventricle", "susilap_g", ...]``)."""
    return sorted(p.name[:-4] for p in PRESET_DIR.iterdir() if p.name.endswith(".fis"))


def _name(name) -> str:
    name = str(name)
    return name[:-4] if name.endswith(".fis") else name


def preset_path(name: str):
    """The file of preset ``name`` (with or without ``.fis``).

    Raises :class:`ConfigError` naming the preset and listing the known ones when there is none.
    """
    name = _name(name)
    known = list_presets()
    if name not in known:
        raise ConfigError("preset", f"one of {', '.join(known)}", got=name)
    return PRESET_DIR / f"{name}.fis"


@functools.cache
def _text(name: str) -> str:
    return preset_path(name).read_text(encoding="utf-8")


def load_preset(name: str) -> MamdaniSystem:
    """A fresh :class:`MamdaniSystem` read from preset ``name`` (see :func:`list_presets`)."""
    name = _name(name)
    return parse_fis(_text(name), path=f"{name}.fis")


@functools.cache
def _library() -> dict:
    path = PRESET_DIR / TISSUE_FILE
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:  # a broken edit of the shipped file
        raise ConfigError("tissue library", f"valid TOML ({e})", got=None, file=str(path)) from None


def tissues() -> dict:
    """The tissue library from ``fuzzy/tissues.toml`` (a copy; edit freely).

    ``{name: {"consistency", "term", "youngs_modulus_range" [Pa], "density" [kg/m^3],
    "poisson_ratio", "source"}}``.
    """
    return copy.deepcopy(_library()["tissues"])


def tissue_parameters(name: str, *, system: MamdaniSystem | None = None) -> dict:
    """Material parameters of tissue ``name`` in SI units, from the tissue library's fuzzy system.

    Args:
        name: a key of :func:`tissues` (``"liver"``, ``"brain"``, ...; any case: ``"Liver"``).
        system: the system to evaluate; default the library's own (``tissue_si``).

    Returns:
        ``{"youngs_modulus": E [Pa], "viscosity": eta [Pa*s], "density": rho [kg/m^3],
        "poisson_ratio": nu (from the literature, nearly incompressible), "consistency": input value,
        "term": its linguistic term, "youngs_modulus_range": (lo, hi) [Pa] from the literature}``.
    """
    lib = tissues()
    key = name.strip().lower() if isinstance(name, str) else name
    if key not in lib:
        raise ConfigError("tissue", f"one of {', '.join(sorted(lib))} (any case)", got=name)
    entry = lib[key]
    fis = system if system is not None else load_preset(_library()["system"])
    out = fis.evaluate(consistency=float(entry["consistency"]))
    lo, hi = entry["youngs_modulus_range"]
    return {
        "youngs_modulus": float(out["youngs_modulus"]),
        "viscosity": float(out["viscosity"]),
        "density": float(entry["density"]),
        "poisson_ratio": float(entry["poisson_ratio"]),
        "consistency": float(entry["consistency"]),
        "term": entry["term"],
        "youngs_modulus_range": (float(lo), float(hi)),
    }


# ------------------------------------------------------------------ tissue words -> elastic solid
TISSUE_EXPECTED = (
    "a tissue of the fuzzy library (brain, fat, liver, ...), a consistency term (very_soft, soft, "
    "medium, firm, hard) or a consistency value in [0, 10]"
)


def tissue_expected() -> str:
    """What a tissue value may be, with every tissue and term name (for errors).

    Examples:
        >>> "liver_cirrhotic" in tissue_expected() and "very_soft" in tissue_expected()
        True
    """
    var = cast("Variable", load_preset(_library()["system"]).inputs[0])
    return (
        f"a tissue of the fuzzy library ({', '.join(sorted(_library()['tissues']))}), a consistency term "
        f"({', '.join(var.term_names)}) or a consistency value in [0, 10] (names in any case)"
    )


#: The Poisson ratio of a consistency term or number (no tissue of the library, so no measured ratio):
#: soft tissue is nearly incompressible; 0.45 keeps explicit time steps about twice those of 0.49
DEFAULT_POISSON_RATIO = 0.45


def tissue_properties(values, *, key: str = "tissue") -> list:
    """The elastic solid of tissue words or consistency values, from the fuzzy tissue library.

    Each value is a tissue of :func:`torchdeform.fuzzy.tissues` (its consistency), a term of the
    ``consistency`` input of the library's system ``tissue_si`` (the middle of the term's plateau)
    or a consistency number in ``[0, 10]``; the system turns the consistency into a Young's modulus
    and a viscosity. The system is evaluated once for all values.

    Returns:
        one dict per value: ``youngs_modulus`` E (Pa) and ``viscosity`` eta (Pa s) of the system,
        ``poisson_ratio`` nu (the library's for a tissue, :data:`DEFAULT_POISSON_RATIO` for a term
        or a number) and ``density`` (kg/m^3, the library's for a tissue, None for a term or a number).

    Raises:
        ConfigError: (naming ``key``) a value that is none of these.

    Examples:
        >>> liver, soft = tissue_properties(["liver", "soft"])
        >>> round(liver["youngs_modulus"]), liver["poisson_ratio"], liver["density"]
        (3700, 0.49, 1060.0)
        >>> soft["poisson_ratio"], soft["density"]
        (0.45, None)
    """
    library, fis = tissues(), load_preset("tissue_si")
    var = cast("Variable", fis.inputs[0])  # a system's inputs are variables
    consistency, out = [], []
    for original in values:
        v = original
        if isinstance(v, str):  # names in any case: "Liver" is "liver"
            v = v.strip().lower()
        if isinstance(v, str) and v in library:
            entry = library[v]
            consistency.append(float(entry["consistency"]))
            out.append({"poisson_ratio": float(entry["poisson_ratio"]), "density": float(entry["density"])})
            continue
        if isinstance(v, str) and v in var.term_names:
            consistency.append(float(cast("MembershipFunction", var.terms[v]).peak()))
        elif isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 10:
            consistency.append(float(v))
        else:
            raise ConfigError(key, tissue_expected(), got=original)
        out.append({"poisson_ratio": DEFAULT_POISSON_RATIO, "density": None})
    if not out:
        return []
    y = fis(torch.tensor(consistency, dtype=fis.dtype).view(-1, 1))
    names = fis.output_names()
    for row, props in zip(y, out):
        props["youngs_modulus"] = float(row[names.index("youngs_modulus")])
        props["viscosity"] = float(row[names.index("viscosity")])
    return out


def tissue_moduli(values, *, key: str = "tissue") -> list:
    """Young's moduli (Pa) of tissue words or consistency values, from the fuzzy tissue library.

    The ``youngs_modulus`` of :func:`tissue_properties`.

    Examples:
        >>> E = tissue_moduli(["fat", "hard", 5.0])
        >>> [round(e / 1000, 1) for e in E]            # kPa
        [2.8, 58.5, 11.0]
    """
    return [p["youngs_modulus"] for p in tissue_properties(values, key=key)]

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

from ..errors import ConfigError
from .fis import parse_fis
from .system import MamdaniSystem

__all__ = ["PRESET_DIR", "TISSUE_FILE", "list_presets", "preset_path", "load_preset", "tissues", "tissue_parameters"]

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
        name: a key of :func:`tissues` (``"liver"``, ``"brain"``, ...).
        system: the system to evaluate; default the library's own (``tissue_si``).

    Returns:
        ``{"youngs_modulus": E [Pa], "viscosity": eta [Pa*s], "density": rho [kg/m^3],
        "poisson_ratio": nu (from the literature, nearly incompressible), "consistency": input value,
        "term": its linguistic term, "youngs_modulus_range": (lo, hi) [Pa] from the literature}``.
    """
    lib = tissues()
    if name not in lib:
        raise ConfigError("tissue", f"one of {', '.join(sorted(lib))}", got=name)
    entry = lib[name]
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

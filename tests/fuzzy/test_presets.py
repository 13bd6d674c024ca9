"""The shipped rule files (fuzzy/*.fis, fuzzy/tissues.toml) and torchdeform.fuzzy.presets.

- Radetzky's published input/output pairs come out of the presets to 1e-3 relative (the files
  are fitted to 1e-4; their membership functions are reconstructions);
- the rule tables are exactly Tables C.1 and C.2, written out here independently of the files;
- every Radetzky file says in its header that its membership functions are reconstructions;
- the SI tissue library is consistent with its fuzzy system.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from torchdeform.errors import ConfigError
from torchdeform.fuzzy import MamdaniSystem, presets
from torchdeform.fuzzy.fis import parse_fis

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[2]
FUZZY = REPO / "fuzzy"

# ---------------------------------------------------------------- the published data (thesis appendix C)

#: Table C.1: consistency term -> (spring_const term, viscosity term), in the printed order
TABLE_C1 = [
    ("flexible", "small", "small"),
    ("muscular", "very_large", "medium"),
    ("pudding", "small", "very_large"),
    ("wobbly", "small", "very_small"),
    ("very_soft", "very_small", "very_large"),
    ("soft", "small", "large"),
    ("medium", "medium", "medium"),
]
#: Table C.2: (input, term) -> spring_const term, viscosity term (None: rule sets spring_const only)
TABLE_C2 = [
    ("consistency", "solid", "very_large", None),
    ("consistency", "hard", "large", None),
    ("consistency", "soft", "small", None),
    ("consistency", "wobbly", "medium", "small"),
    ("consistency", "doughy", "very_small", "very_large"),
    ("consistency", "mushy", "large", "large"),
    ("sensitiveness", "very_large", "very_small", "very_small"),
    ("sensitiveness", "large", "small", "small"),
    ("sensitiveness", "medium", "medium", "medium"),
    ("sensitiveness", "small", "small", "large"),
    ("sensitiveness", "very_small", "very_small", "very_large"),
    ("shiftability", "large", "medium", "very_large"),
    ("shiftability", "medium", "small", "medium"),
    ("shiftability", "small", "small", "very_small"),
]
FIVE = {"very_small", "small", "medium", "large", "very_large"}

#: (preset, inputs, spring_const, viscosity) from the text of appendix C
GOLDEN = [
    ("susilap_g", {"consistency": 5.5}, 16.2606, 2.87713),  # Fallopian tube
    ("susilap_g", {"consistency": 2.5}, 2.41327, 10.6875),  # tube-background anchors
    ("susilap_g", {"consistency": 10.1}, 81.3091, 6.0),  # uterus
    ("susilap_g", {"consistency": 7.0}, 11.3536, 9.13015),  # bowel
    ("robo_sim_ventricle", {"consistency": 7.3, "sensitiveness": 4.9, "shiftability": 3.0}, 45.4871, 72.8125),
]


@pytest.fixture(scope="module")
def susilap():
    return presets.load_preset("susilap_g")


@pytest.fixture(scope="module")
def robo():
    return presets.load_preset("robo_sim_ventricle")


# ---------------------------------------------------------------- golden values


@pytest.mark.parametrize(
    "name, inputs, spring, viscosity", GOLDEN, ids=[f"{g[0]}-{'-'.join(map(str, g[1].values()))}" for g in GOLDEN]
)
def test_published_values(name, inputs, spring, viscosity, device):
    fis = presets.load_preset(name).to(device)
    out = fis.evaluate(**inputs)
    assert out["spring_const"].device == device
    assert float(out["spring_const"]) == pytest.approx(spring, rel=1e-3)
    assert float(out["viscosity"]) == pytest.approx(viscosity, rel=1e-3)


def test_published_values_in_float64_and_batched(device):
    """The same numbers from a float64 copy and from one batched call (no float32 luck)."""
    fis = presets.load_preset("susilap_g").to(torch.float64).to(device)
    x = torch.tensor([g[1]["consistency"] for g in GOLDEN[:4]], dtype=torch.float64, device=device)
    out = {k: v.cpu() for k, v in fis.evaluate(consistency=x).items()}
    want_s = torch.tensor([g[2] for g in GOLDEN[:4]], dtype=torch.float64)
    want_v = torch.tensor([g[3] for g in GOLDEN[:4]], dtype=torch.float64)
    assert torch.allclose(out["spring_const"], want_s, rtol=1e-3, atol=0)
    assert torch.allclose(out["viscosity"], want_v, rtol=1e-3, atol=0)


def test_presets_use_default_inference(susilap, robo):
    """The golden values hold for the engine's defaults, which the files must not override."""
    for fis in (susilap, robo):
        assert (fis.and_method, fis.or_method, fis.implication, fis.aggregation, fis.defuzzification) == (
            "min",
            "max",
            "min",
            "max",
            "centroid",
        )
        assert fis.resolution == 1000


# ---------------------------------------------------------------- rule tables exactly as published


def _rules(fis):
    """Each rule as ((input, term), {output: term}), with checks that nothing else is in it."""
    out = []
    for rule in fis.rules:
        assert rule.weight == 1.0 and rule.connective == "and"
        assert len(rule.antecedent) == 1, "Radetzky's rules have a single antecedent"
        (a,) = rule.antecedent
        assert a.hedges == ()
        cons = {}
        for c in rule.consequent:
            assert c.hedges == ()
            cons[c.variable] = c.term
        out.append(((a.variable, a.term), cons))
    return out


def test_susilap_rule_table(susilap):
    assert [v.name for v in susilap.inputs] == ["consistency"]
    assert [v.name for v in susilap.outputs] == ["spring_const", "viscosity"]
    want = [(("consistency", c), {"spring_const": s, "viscosity": v}) for c, s, v in TABLE_C1]
    assert _rules(susilap) == want
    assert set(susilap.inputs[0].term_names) == {c for c, _, _ in TABLE_C1}


def test_robo_rule_table(robo):
    assert [v.name for v in robo.inputs] == ["consistency", "sensitiveness", "shiftability"]
    assert [v.name for v in robo.outputs] == ["spring_const", "viscosity"]
    want = [((var, term), {"spring_const": s, **({"viscosity": v} if v else {})}) for var, term, s, v in TABLE_C2]
    assert _rules(robo) == want
    terms = {v.name: set(v.term_names) for v in (*robo.inputs, *robo.outputs)}
    assert terms == {
        "consistency": {"solid", "hard", "soft", "wobbly", "doughy", "mushy"},
        "sensitiveness": FIVE,
        "shiftability": {"small", "medium", "large"},
        "spring_const": FIVE,
        "viscosity": FIVE,
    }


def test_robo_rules_1_to_3_have_no_viscosity_in_the_file():
    """In the .fis text rules 1-3 carry output index 0 (no consequent) for viscosity."""
    lines = FUZZY.joinpath("robo_sim_ventricle.fis").read_text().split("[Rules]")[1].split("\n")
    rules = [ln.split("(")[0] for ln in lines if ln.strip()]
    assert len(rules) == 14
    assert [r.split(",")[1].split()[1] for r in rules[:3]] == ["0", "0", "0"]
    assert all(r.split(",")[1].split()[1] != "0" for r in rules[3:])


def test_membership_functions_are_trapezoid_partitions(susilap, robo):
    """Reconstructed terms are trapezoids inside their variable's range, normal, ordered along
    the axis, and every point of an input range belongs to some term."""
    for fis in (susilap, robo):
        for var in (*fis.inputs, *fis.outputs):
            is_input = any(var is v for v in fis.inputs)
            lo, hi = var.range
            peaks = []
            for term, mf in var.terms.items():
                assert mf.kind == "trapezoid", (var.name, term)
                a, b, c, d = mf.values()
                assert lo <= a <= b <= c <= d <= hi, (var.name, term, mf.values())
                peaks.append(0.5 * (b + c))
                assert float(mf(torch.tensor([0.5 * (b + c)]))[0]) == 1.0, (var.name, term)  # normal
            assert peaks == sorted(peaks), f"{var.name}: terms not in axis order"
            if is_input:
                x = torch.linspace(lo, hi, 2001)
                mu = torch.stack([mf(x) for mf in var.terms.values()])
                assert float(mu.amax(dim=0).min()) > 0, f"{var.name}: a gap between terms"


def test_susilap_viscosity_medium_is_symmetric_about_6(susilap):
    """The uterus' viscosity of exactly 6 comes from one medium term centred at 6 (REFERENCE 3.1)."""
    a, b, c, d = susilap.outputs[1].terms["medium"].values()
    assert a + d == pytest.approx(12.0) and b + c == pytest.approx(12.0)
    assert float(susilap.evaluate(consistency=10.1)["viscosity"]) == pytest.approx(6.0, rel=1e-6)


# ---------------------------------------------------------------- the reconstruction note


def _header(name):
    text = FUZZY.joinpath(f"{name}.fis").read_text(encoding="utf-8")
    head = text.split("[System]")[0]
    lines = head.strip().splitlines()
    assert lines and all(ln.startswith("%") for ln in lines), "header lines must be % comments"
    return " ".join(ln.lstrip("% ").strip() for ln in lines)


@pytest.mark.parametrize("name, table", [("susilap_g", "Table C.1"), ("robo_sim_ventricle", "Table C.2")])
def test_reconstruction_note_in_header(name, table):
    head = _header(name)
    assert "Radetzky" in head and "appendix C" in head and table in head
    assert "RECONSTRUCTION" in head and "NOT Radetzky's originals" in head
    assert "Figs. C.1-C.8 are lost" in head
    assert "Units: not given in the source" in head
    for preset, inputs, spring, viscosity in GOLDEN:  # the pairs the corners were fitted to
        if preset == name:
            for number in (*inputs.values(), spring, viscosity):
                assert f"{number}" in head, f"{number} not listed in the header of {name}.fis"


def test_headers_are_ignored_by_the_reader():
    """Reading the file and reading it without its header give the same system."""
    for name in ("susilap_g", "robo_sim_ventricle", "tissue_si"):
        text = FUZZY.joinpath(f"{name}.fis").read_text(encoding="utf-8")
        bare = parse_fis("[System]" + text.split("[System]", 1)[1])
        full = presets.load_preset(name)
        for v1, v2 in zip((*bare.inputs, *bare.outputs), (*full.inputs, *full.outputs)):
            assert {t: mf.values() for t, mf in v1.terms.items()} == {t: mf.values() for t, mf in v2.terms.items()}


# ---------------------------------------------------------------- presets API


def test_list_and_load_presets():
    names = presets.list_presets()
    assert names == sorted(names)
    assert {"susilap_g", "robo_sim_ventricle", "tissue_si"} <= set(names)
    assert {p.stem for p in FUZZY.glob("*.fis")} == set(names)
    for name in names:
        fis = presets.load_preset(name)
        assert isinstance(fis, MamdaniSystem) and fis.name == name
    assert presets.load_preset("susilap_g.fis").name == "susilap_g"


def test_load_preset_gives_fresh_systems():
    a = presets.load_preset("susilap_g")
    a.outputs[0].terms["very_large"].raw.data += 10.0
    b = presets.load_preset("susilap_g")
    assert float(b.evaluate(consistency=10.1)["spring_const"]) == pytest.approx(81.3091, rel=1e-3)


def test_unknown_preset_names_it_and_lists_the_known_ones():
    with pytest.raises(ConfigError) as err:
        presets.load_preset("susilap_h")
    msg = str(err.value)
    assert "susilap_h" in msg
    for name in presets.list_presets():
        assert name in msg
    with pytest.raises(ConfigError):
        presets.preset_path("nope")


def test_preset_dir_holds_the_repository_files():
    """Whatever install mode, the files torchdeform finds are the repository's fuzzy/ files."""
    for name in presets.list_presets():
        assert presets.preset_path(name).read_text(encoding="utf-8") == FUZZY.joinpath(f"{name}.fis").read_text(
            encoding="utf-8"
        )
    assert presets.PRESET_DIR.joinpath("tissues.toml").read_text(encoding="utf-8") == FUZZY.joinpath(
        "tissues.toml"
    ).read_text(encoding="utf-8")


def test_pyproject_ships_the_rule_files():
    """A plain (non-editable) install maps the data package torchdeform.rulefiles onto fuzzy/ and
    includes the .fis, .toml and .md files (checked for real by building: see fuzzy/README.md)."""
    st = tomllib.loads(REPO.joinpath("pyproject.toml").read_text())["tool"]["setuptools"]
    assert {"torchdeform", "torchdeform.fuzzy", "torchdeform.rulefiles"} <= set(st["packages"])
    assert st["package-dir"]["torchdeform.rulefiles"] == "fuzzy"
    assert {"*.fis", "*.toml"} <= set(st["package-data"]["torchdeform.rulefiles"])
    assert FUZZY.joinpath("__init__.py").is_file()


# ---------------------------------------------------------------- SI tissue library


def test_tissue_library_entries():
    lib = presets.tissues()
    assert {"liver", "fat", "muscle", "brain", "kidney"} <= set(lib)
    for name, t in lib.items():
        lo, hi = t["youngs_modulus_range"]
        assert 0 < lo < hi, name
        assert 900 <= t["density"] <= 1100, name  # soft tissue, kg/m^3
        assert isinstance(t["source"], str) and len(t["source"]) > 20, name
        assert 0 <= t["consistency"] <= 10, name
    liver = lib["liver"]["youngs_modulus_range"]
    assert liver[0] <= 1000 and liver[1] >= 7000  # healthy liver ~0.5-10 kPa
    lib["liver"]["density"] = -1.0  # tissues() hands out a copy
    assert presets.tissues()["liver"]["density"] > 0


def test_tissue_moduli_fall_in_their_literature_ranges():
    fis = presets.load_preset("tissue_si")
    assert [v.name for v in fis.outputs] == ["youngs_modulus", "viscosity"]
    cons = fis.inputs[0]
    for name, t in presets.tissues().items():
        c = torch.tensor([float(t["consistency"])])
        out = fis.evaluate(consistency=c)
        e = float(out["youngs_modulus"][0])
        lo, hi = t["youngs_modulus_range"]
        assert lo <= e <= hi, f"{name}: E = {e:.0f} Pa outside [{lo:.0f}, {hi:.0f}]"
        mu = {term: float(mf(c)[0]) for term, mf in cons.terms.items()}
        assert max(mu, key=mu.get) == t["term"], f"{name}: {t['consistency']} is mostly {max(mu, key=mu.get)}"
        eta = float(out["viscosity"][0])
        assert 0 < eta <= fis.outputs[1].range[1]


def test_tissue_si_is_monotone_in_consistency():
    fis = presets.load_preset("tissue_si")
    out = fis.evaluate(consistency=torch.linspace(0, 10, 201))
    e = out["youngs_modulus"]
    assert bool((e[1:] >= e[:-1] - 1e-3 * e[:-1]).all())
    assert float(e[0]) < 2000 and float(e[-1]) > 40000


def test_tissue_parameters():
    p = presets.tissue_parameters("liver")
    assert set(p) >= {"youngs_modulus", "viscosity", "density", "consistency", "term", "youngs_modulus_range"}
    lo, hi = p["youngs_modulus_range"]
    assert lo <= p["youngs_modulus"] <= hi
    assert p["density"] == presets.tissues()["liver"]["density"]
    assert all(math.isfinite(p[k]) for k in ("youngs_modulus", "viscosity", "density"))
    stiffer = presets.tissue_parameters("liver_cirrhotic")
    assert stiffer["youngs_modulus"] > p["youngs_modulus"]
    with pytest.raises(ConfigError) as err:
        presets.tissue_parameters("spleen")
    assert "spleen" in str(err.value) and "liver" in str(err.value)

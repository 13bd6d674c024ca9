"""Scenes of several bodies (``[[bodies]]``, :mod:`torchdeform.scene.bodies`): ``scenes/organs.toml`` and bad input.

Oracles, independent of the contact code's own readings where they can be:

- interpenetration: besides the run's penetration series (the deepest node before each projection),
  every liver node at every recorded frame is compared with the kidney's deformed top surface,
  interpolated linearly over a Delaunay triangulation of its top nodes (scipy), not with the
  trilinear cells the contact code locates points in; tolerance ``PENETRATION_TOL``;
- load balance: once the liver has settled on the kidney, the contact force is its weight
  (``m g``, the model's lumped masses), and the kidney's base carries both bodies plus the probe's
  press (the force the tool reading reports);
- bad input: the command line's contract, exit status 2 and one line naming file, line and key
  (lines counted here from the scene text).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from torchdeform.cli import main
from torchdeform.scene import load_scene

ROOT = Path(__file__).resolve().parents[2]
ORGANS = ROOT / "scenes" / "organs.toml"
G = 9.81
#: deepest overlap of the two bodies allowed at a recorded frame (m): 0.1 mm, 2.5 % of the 4 mm spacing
PENETRATION_TOL = 1e-4
#: relative tolerance of the settled contact force against the liver's weight (frame-to-frame ripple ~5 %)
WEIGHT_RTOL = 0.05
#: the settled window (s): after the drop's bounces have decayed, before the probe presses
SETTLED = (0.15, 0.2)


@pytest.fixture(scope="module")
def organs(tmp_path_factory):
    """``torchdeform run scenes/organs.toml`` once: (stdout, summary, trajectory, scene)."""
    out = tmp_path_factory.mktemp("organs")
    import contextlib
    import io

    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        status = main(argv=["run", str(ORGANS), "--out", str(out), "--quiet"])
    assert status == 0
    summary = json.loads((out / "summary.json").read_text())
    with np.load(out / "trajectory.npz") as z:
        traj = {k: z[k] for k in z.files}
    return stdout.getvalue(), summary, traj, load_scene(ORGANS), out


def test_organs_runs_and_writes_its_outputs(organs):
    stdout, summary, traj, scene, out = organs
    assert len(stdout.strip().splitlines()) == 1 and "2 bodies" in stdout and "not animated" not in stdout
    assert "animation.gif" in stdout
    assert sorted(summary["outputs"]) == ["animation.gif", "contact.png", "summary.json", "trajectory.npz"]
    assert (out / "contact.png").stat().st_size > 10_000
    assert scene.names == ["kidney", "liver"] and summary["steps"] == scene.steps == 900
    T = len(summary["t_s"])
    assert traj["kidney.x"].shape == (T, 3, 6, 7, 7) and traj["liver.x"].shape == (T, 3, 6, 6, 6)
    assert np.allclose(traj["t"], summary["t_s"]) and traj["t"][-1] == pytest.approx(summary["simulated_time_s"])
    pair = summary["contact"]["kidney/liver"]
    assert len(pair["force_N"]) == len(pair["contacts"]) == len(pair["penetration_m"]) == T
    assert pair["max_contacts"] > 0 and pair["max_force_N"] > 0
    for name in ("kidney", "liver"):
        body = summary["bodies"][name]
        assert body["peak_displacement_m"] >= body["final_displacement_m"] > 0
    # the liver fell its 3 mm gap and more; the stiffer kidney gave less than half a millimetre
    assert summary["bodies"]["liver"]["final_displacement_m"] > 3e-3
    assert summary["bodies"]["kidney"]["peak_displacement_m"] < 0.5e-3
    assert "not_drawn" not in summary


def _hue_masks(frame: np.ndarray) -> tuple:
    """Pixels of the surface panel (left half, above the caption) of the kidney's and of the liver's colour."""
    from torchdeform.scene.animation import BODY_COLOURS

    rgb = frame.astype(float)
    panel = np.zeros(frame.shape[:2], bool)
    panel[: frame.shape[1] // 2, : frame.shape[1] // 2] = True
    masks = []
    for colour in BODY_COLOURS[:2]:  # shaded: the hue kept, the brightness not; chroma well above grey
        c = np.asarray(colour) / np.linalg.norm(colour)
        norm = np.linalg.norm(rgb, axis=-1) + 1e-9
        chroma = rgb.max(-1) - rgb.min(-1)
        masks.append(panel & ((rgb @ c) / norm > 0.99) & (chroma > 40))
    return tuple(masks)


def test_organs_animation_shows_both_bodies_and_the_drop(organs):
    """Oracle: pixel colours. Both organs' colours (kidney, liver in BODY_COLOURS order) are in the frames;
    the liver's pixels move down the image while it drops its 3 mm gap, the kidney's base stays."""
    from PIL import Image

    _, summary, _, _, out = organs
    anim = summary["animation"]
    assert anim["colours"] == {"kidney": [204, 107, 92], "liver": [102, 148, 209]}
    assert anim["frames"] >= 20 and anim["size"] == [256 + 28, 512]
    frames = []
    with Image.open(out / "animation.gif") as gif:
        assert gif.n_frames == anim["frames"]
        for k in range(gif.n_frames):
            gif.seek(k)
            frames.append(np.asarray(gif.convert("RGB")))
    t = np.linspace(0.0, summary["t_s"][-1], len(frames))
    settled = int(np.searchsorted(t, SETTLED[1]))  # before the probe presses
    rows = {}
    for k in (0, settled):
        kidney, liver = _hue_masks(frames[k])
        assert kidney.sum() > 500 and liver.sum() > 500, (k, kidney.sum(), liver.sum())
        rows[k] = (np.nonzero(kidney.any(1))[0].max(), np.nonzero(liver.any(1))[0].min(), np.nonzero(liver)[0].mean())
    # the liver fell: its top edge and its pixels' mean row lower in the image (rows grow downwards)
    assert rows[settled][1] >= rows[0][1] + 5 and rows[settled][2] >= rows[0][2] + 3, rows
    assert abs(int(rows[settled][0]) - int(rows[0][0])) <= 1  # the kidney's base is fixed


def test_organs_do_not_interpenetrate(organs):
    from scipy.interpolate import LinearNDInterpolator

    _, summary, traj, _, _ = organs
    assert max(summary["contact"]["kidney/liver"]["penetration_m"]) < PENETRATION_TOL
    gaps = []
    for x_k, x_l in zip(traj["kidney.x"], traj["liver.x"]):
        top = x_k[:, -1].reshape(3, -1)  # the kidney's top layer of nodes, deformed
        surface = LinearNDInterpolator(top[1:].T, top[0])
        nodes = x_l.reshape(3, -1)
        height = surface(nodes[1:].T)  # NaN outside the kidney's footprint
        over = np.isfinite(height)
        assert over.sum() >= 36  # the liver's whole bottom layer lies over the kidney
        gaps.append(float((nodes[0][over] - height[over]).min()))
    gaps = np.array(gaps)
    assert gaps.min() > -PENETRATION_TOL, f"deepest overlap {-gaps.min() * 1e3:.3f} mm"
    settled = (traj["t"] > SETTLED[0]) & (traj["t"] < SETTLED[1])
    assert np.abs(gaps[settled]).max() < PENETRATION_TOL  # resting on it: touching, not floating


def test_settled_contact_force_is_the_liver_weight(organs):
    _, summary, _, scene, _ = organs
    masses = {n: float(s.build().mass.expand(1, 1, *s.grid.shape).sum()) for n, s in zip(scene.names, scene.scenes)}
    t = np.array(summary["t_s"])
    force = np.array(summary["contact"]["kidney/liver"]["force_N"])  # kidney on liver, (T, 3)
    window = (t > SETTLED[0]) & (t < SETTLED[1])
    assert window.sum() >= 10
    weight = masses["liver"] * G
    assert force[window, 0].mean() == pytest.approx(weight, rel=WEIGHT_RTOL)
    assert np.abs(force[window, 1:]).max() < 1e-3 * weight  # straight up: nothing pushes sideways
    # at the end the probe presses the liver: the kidney's base carries both bodies and the press
    press = summary["bodies"]["liver"]["tools"]["probe"]["final_force_N"][0]
    assert press > 0.2 * weight
    support = summary["bodies"]["kidney"]["support_reaction_N"][0]
    assert support == pytest.approx((masses["kidney"] + masses["liver"]) * G + press, rel=WEIGHT_RTOL)


# ------------------------------------------------------------------ bad input
TWO = """\
[[bodies]]
name = "lower"

[bodies.grid]
shape = [3, 3, 3]
spacing = 0.01
origin = [0.0, 0.0, 0.0]

[bodies.material]
stiffness = 50.0

[bodies.mass]
mass = 0.001

[bodies.boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]

[[bodies]]
name = "upper"

[bodies.grid]
shape = [3, 3, 3]
spacing = 0.01
origin = [0.025, 0.0, 0.0]

[bodies.material]
stiffness = 50.0

[bodies.mass]
mass = 0.001

[[bodies.tools]]
name = "probe"
shape = "sphere"
radius = 0.004
position = [0.05, 0.01, 0.01]

[bodies.boundary]
gravity = [-9.81, 0.0, 0.0]

[integrator]
dt = 1e-3
steps = 4
"""


def _line(text: str, needle: str, nth: int = 0) -> int:
    """1-based line of the ``nth`` line of ``text`` that starts with ``needle``."""
    hits = [i + 1 for i, line in enumerate(text.splitlines()) if line.startswith(needle)]
    return hits[nth]


def _run(tmp_path, text, capsys, *extra):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    status = main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet", *extra])
    captured = capsys.readouterr()
    return path, status, captured


def test_two_bodies_run_from_the_command_line(tmp_path, capsys):
    _, status, captured = _run(tmp_path, TWO, capsys, "--set", "output.name=pair")
    assert status == 0, captured.err
    assert captured.out.startswith("pair: 2 bodies, 4 symplectic steps")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert set(summary["bodies"]) == {"lower", "upper"} and "lower/upper" in summary["contact"]
    assert "probe" in summary["bodies"]["upper"]["tools"]


BAD = {
    # name: (edit of TWO, key, (line start, nth match))
    "overlap": (("origin = [0.0, 0.0, 0.0]", "origin = [0.01, 0.0, 0.0]"), "bodies[0].grid.origin", ("origin", 0)),
    "no name": (('name = "upper"\n', ""), "bodies[1].name", ("[[bodies]]", 1)),
    "same name": (('name = "upper"', 'name = "lower"'), "bodies[1].name", ('name = "lower"', 1)),
    "top-level grid": (("[integrator]", "[grid]\nshape = [2, 2, 2]\n\n[integrator]"), "grid", ("[grid]", 0)),
    "value in a body": (("stiffness = 50.0", "stiffness = -5.0", 2), "bodies[1].material.stiffness", ("stiffness", 1)),
    "key in a body": (("mass = 0.001", "mas = 0.001", 2), "bodies[1].mass.mas", ("mas =", 0)),
    "tool of a body": (("radius = 0.004", "radius = -0.004"), "bodies[1].tools[0].radius", ("radius", 0)),
    "global section in a body": (
        ("[bodies.boundary]\ngravity", "[bodies.integrator]\ndt = 1e-3\n\n[bodies.boundary]\ngravity"),
        "bodies[1].integrator",
        ("[bodies.integrator]", 0),
    ),
    "surfaces": (("[integrator]", "[output]\nsurfaces = true\n\n[integrator]"), "output.surfaces", ("surfaces", 0)),
}


def _edit(text: str, edit: tuple) -> str:
    """``text`` with the nth (1-based, default 1) occurrence of ``old`` replaced by ``new``: ``edit = (old, new[, nth])``."""
    old, new, *nth = edit
    parts = text.split(old)
    k = nth[0] if nth else 1
    assert len(parts) > k, edit
    return old.join(parts[:k]) + new + old.join(parts[k:])


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_input_is_one_line_naming_file_and_line(case, tmp_path, capsys):
    edit, key, (needle, nth) = BAD[case]
    text = _edit(TWO, edit)
    path, status, captured = _run(tmp_path, text, capsys)
    assert status == 2, captured.err
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(f"torchdeform: {path}:{_line(text, needle, nth)}: {key}: expected "), lines[0]
    if case == "overlap":
        assert "lower starts inside upper" in lines[0]
    assert not (tmp_path / "out" / "summary.json").exists()


# ------------------------------------------------------------------ one body, as before
def test_single_body_scene_runs_as_before(tmp_path, capsys):
    path = ROOT / "scenes" / "beam_sag.toml"
    status = main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet", "--set", "integrator.steps=10"])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert "bodies" not in summary and summary["steps"] == 10
    assert "energy.png" in summary["outputs"] and captured.out.startswith("beam")


# ------------------------------------------------------------------ --set on a scene of several bodies
def test_run_set_takes_the_contact_and_a_named_bodys_keys(tmp_path):
    from tests.helpers import cli_call

    base = ["run", ORGANS, "--set", "integrator.steps=20", "--quiet"]
    status, _, err = cli_call([*base, "--out", tmp_path / "a"])
    assert status == 0, err
    status, _, err = cli_call(
        [
            *base,
            "--set",
            "contact.friction=0.1",
            "--set",
            "bodies.kidney.material.poisson_ratio=0.4",
            "--out",
            tmp_path / "b",
        ]
    )
    assert status == 0, err
    a, b = (json.loads((tmp_path / n / "summary.json").read_text()) for n in "ab")
    assert a["friction"] == 0.3 and b["friction"] == 0.1
    assert b["time_step_bound_s"] > 1.05 * a["time_step_bound_s"]  # a lower Poisson ratio: a longer stable step
    for args, key in (
        (["--set", "bodies.spleen.material.poisson_ratio=0.4"], "kidney, liver"),
        (["--set", "bodies.kidney.material.poisson_ratio=0.7"], "--set bodies.kidney.material.poisson_ratio"),
        (["--set", "bodies.kidney.tools.radius=0.1"], "bodies.NAME.SECTION.KEY"),
    ):
        status, _, err = cli_call([*base, *args, "--out", tmp_path / "c"])
        assert status == 2 and len(err.strip().splitlines()) == 1 and key in err, err


def test_sweep_refuses_a_scene_of_several_bodies_in_one_line(tmp_path):
    from tests.helpers import cli_call

    status, _, err = cli_call(["sweep", ORGANS, "--set", "integrator.steps=10,20", "--out", tmp_path / "s", "--quiet"])
    assert status == 2 and len(err.strip().splitlines()) == 1 and "[[bodies]] scene is not swept yet" in err, err


def test_a_tool_out_of_reach_is_named_inside_its_body(tmp_path):
    """A probe path in millimetres: the warning names bodies[1].tools[0].path and its line."""
    import warnings

    from torchdeform.errors import ConfigWarning

    text = ORGANS.read_text()
    old = "path = [[0.0, [0.0453, 0.012, 0.012]], [0.2, [0.0453, 0.012, 0.012]], [0.3, [0.041, 0.012, 0.012]]]"
    assert old in text
    f = tmp_path / "mm.toml"
    f.write_text(text.replace(old, "path = [[0.0, [45.3, 12.0, 12.0]], [0.3, [41.0, 12.0, 12.0]]]"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_scene(f)
    lines = [str(w.message) for w in caught if issubclass(w.category, ConfigWarning)]
    line = next(n for n, s in enumerate(f.read_text().splitlines(), 1) if s.startswith("path = [[0.0, [45.3"))
    assert any(m.startswith(f"{f}:{line}: bodies[1].tools[0].path: tool 'probe' never comes within") for m in lines), (
        lines
    )

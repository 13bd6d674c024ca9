"""``scenes/liver.toml``: palpating the phantom's liver finds its tumour.

Oracle: the same scene with the tumour given the liver's own material (a control). The presses
of the scene are cut down to two (over the tumour, and 24 mm away along the line, beyond the
tumour's radius plus the probe's) so the test runs in about ten seconds; the whole scene's
seven presses are in docs/guide/anatomy.md with the command that produced them.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from torchdeform.scene import load_scene, run_scene

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "liver.toml"
TUMOUR = "youngs_modulus = 4.0e4\npoisson_ratio = 0.45\ndensity = 1060.0"


def _presses(text: str) -> list[str]:
    """The path's lines, one press each (three points: above, deepest, above)."""
    body = re.search(r"^path = \[\n(.*?)\n\]", text, flags=re.S | re.M)
    assert body is not None
    return body.group(1).splitlines()


def _retimed(line: str, start: float) -> str:
    """A press line moved to begin at ``start`` (s)."""
    times = [float(v) for v in re.findall(r"\[(\d+\.\d+), \[", line)]
    for t in sorted(times, reverse=True):
        line = line.replace(f"[{t:.2f}, [", f"[{start + t - times[0]:.2f}, [")
    return line


def _run(tmp_path: Path, name: str, text: str, presses: list[str]) -> list[float]:
    """Peak force (N) of each press of a cut-down copy of the scene."""
    path = "path = [\n" + "\n".join(_retimed(p, 0.15 * i) for i, p in enumerate(presses)) + "\n]"
    text = re.sub(r"^path = \[\n.*?\n\]", lambda _: path, text, flags=re.S | re.M)
    scene_file = tmp_path / f"{name}.toml"
    scene_file.write_text(text)
    scene = load_scene(scene_file)
    scene.steps = scene.steps * len(presses) // 7  # the scene's steps cover its seven presses
    scene.threads = 1  # one core each: the suite runs a test per core
    # the peaks come from the probe's readings of every step: frames at the start and the end only
    # (a hundred frames' energies, support reactions and positions cost a fifth of the run)
    scene.record_every = scene.steps
    summary = run_scene(scene, tmp_path / name, progress=False)
    points = summary["palpation"]["points"]
    assert len(points) == len(presses)
    return [p["peak_force_N"] for p in points]


@pytest.mark.slow
def test_the_force_peaks_over_the_tumour(tmp_path, one_thread):
    text = SCENE.read_text()
    assert TUMOUR in text
    presses = _presses(text)
    assert len(presses) == 7
    away, over = _run(tmp_path, "liver", text, [presses[0], presses[3]])
    assert over >= 1.3 * away, (over, away)
    # the control: the same press over a tumour of liver feels about what the press away does
    (control,) = _run(tmp_path, "control", text.replace(TUMOUR, 'tissue = "liver"'), [presses[3]])
    assert control <= 1.1 * away, (control, away)
    assert over >= 1.25 * control

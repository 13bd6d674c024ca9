"""`torchdeform bench endoscope`: a quick run through the command line (one JSON document, a row per view of
Radetzky's Table 3.1 with his frame rates, the files) and the bench's scene checked by hand (the lumen is
air on its centre line, tissue outside it; the endoscope's camera sits inside)."""

import json
import subprocess
import sys

import pytest

from torchdeform.volume import native_march

pytestmark = pytest.mark.skipif(native_march.unavailable() is not None, reason="no C compiler for the native kernel")


@pytest.mark.slow  # a bench smoke run (a few seconds on 2 cores)
def test_bench_endoscope_quick_json(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "torchdeform", "bench", "endoscope", "--quick", "--json", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)  # exactly one JSON document on stdout
    assert doc["bench"] == "endoscope" and doc["quick"] is True and "machine" in doc
    rows = {row["view"]: row for row in doc["rows"]}
    assert set(rows) == {"overview", "endoscope", "endoscope_voi", "overview_deforming", "endoscope_deforming"}
    radetzky = {"overview": 15, "endoscope": 8, "endoscope_voi": 10, "overview_deforming": 8, "endoscope_deforming": 3}
    for name, row in rows.items():
        assert {"view", "fps", "radetzky_fps", "ratio", "ms_per_frame", "threads", "quick"} <= set(row)
        assert row["fps"] > 0 and row["radetzky_fps"] == radetzky[name] and row["quick"] is True
        assert row["ratio"] == pytest.approx(row["fps"] / row["radetzky_fps"])
    assert rows["endoscope"]["coverage"] > 0.9  # the lumen's wall fills the round image
    assert rows["endoscope_voi"]["far"] == 64.0 and rows["endoscope"]["far"] is None
    assert (tmp_path / "endoscope.csv").is_file() and (tmp_path / "endoscope.png").is_file()


def test_the_lumen_phantom_and_its_transfer_function():
    import torch

    from torchdeform.bench.endoscope import QUICK_VOLUME
    from torchdeform.volume import phantom, preset
    from torchdeform.volume.phantoms import lumen_centre

    vol = phantom(shape=QUICK_VOLUME, lumen=True)
    assert tuple(vol.shape) == QUICK_VOLUME
    plain = phantom(shape=QUICK_VOLUME)
    for s in (0.1, 0.5, 0.9):
        d, h, w = (round(c) for c in lumen_centre(s, QUICK_VOLUME))
        assert float(vol[d, h, w]) == -1000.0 and float(plain[d, h, w]) > -200.0  # air carved into tissue
        assert float(vol[d, h + 8, w]) > -200.0  # tissue beyond the radius (3.2 voxels here)
    _, sigma = preset("ct-lumen")(torch.tensor([-1000.0, 40.0]))
    assert float(sigma[0]) == 0.0 and float(sigma[1]) >= 5.0  # air clear, the wall opaque

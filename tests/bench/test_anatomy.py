"""`torchdeform bench anatomy`: the quick JSON run, and the bench's label volume against its geometry.

Oracles: the analytic volumes of the phantom's ellipsoid and sphere (voxel counts converge to them);
the table's own rows checked for their keys and units (milliseconds, positive) and the plot written.
"""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from torchdeform.bench.anatomy import label_phantom


def test_the_bench_phantom_has_the_volumes_of_its_shapes():
    n = 96
    lab = label_phantom(n)
    organ = 4 / 3 * math.pi * 0.42 * 0.36 * 0.46 * n**3  # voxels, the tumour inside it
    tumour = 4 / 3 * math.pi * 0.11**3 * n**3
    assert int(np.isin(lab, [1, 2]).sum()) == pytest.approx(organ, rel=0.02)
    assert int((lab == 2).sum()) == pytest.approx(tumour, rel=0.05)
    assert (lab == 3).any() and not ((lab == 3) & np.isin(lab, [1, 2])).any()


@pytest.mark.slow  # a bench smoke run
def test_bench_anatomy_quick_json(tmp_path):
    res = subprocess.run(
        [sys.executable, "-m", "torchdeform", "bench", "anatomy", "--quick", "--json", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    rows = {r["row"]: r for r in doc["rows"]}
    assert set(rows) == {"labels -> body", "label surfaces", "surface update"}
    assert all(r["ms"] > 0 and r["threads"] == 2 for r in rows.values())
    assert doc["targets_ms"] == {"labels -> body": 3000.0, "surface update": 5.0}
    assert (tmp_path / "anatomy.csv").is_file() and (tmp_path / "anatomy.png").is_file()

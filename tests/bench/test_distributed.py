"""``torchdeform bench distributed``: a smoke run of one step row on two ranks, its halo bytes
against the analytic size of one layer, and bad options."""

from __future__ import annotations

import json

import pytest

from torchdeform import cli

pytestmark = pytest.mark.slow  # a bench smoke run


def test_a_step_row_on_two_ranks(tmp_path, capsys):
    n = 8
    assert (
        cli.main(
            argv=[
                "bench",
                "distributed",
                "--cases",
                "explicit",
                "--ranks",
                "2",
                "--n",
                str(n),
                "--steps",
                "2",
                "--repeats",
                "1",
                "--json",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    doc = json.loads(capsys.readouterr().out)
    (row,) = doc["rows"]
    assert row["case"] == "explicit" and row["ranks"] == 2 and row["ms_per_step"] > 0
    # one exchange per symplectic step; positions and velocities (damped springs): 6 float32 values per
    # node of an n x n layer, sent to the one neighbour of each rank
    assert row["exchanges_per_step"] == 1 and row["bytes_per_exchange"] == 6 * n * n * 4
    assert 0 < row["comm_share"] < 1
    assert (tmp_path / "distributed.png").stat().st_size > 0 and (tmp_path / "distributed.csv").exists()


@pytest.mark.parametrize("argv", [["--cases", "step"], ["--ranks", "3", "--n", "2"], ["--device", "cuda"]])
def test_bad_options_are_one_line(argv, capsys):
    assert cli.main(argv=["bench", "distributed", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("torchdeform:")

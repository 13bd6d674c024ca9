"""`torchdeform bench bodies`: a quick run through the command line (one JSON document, the row
fields, contact found in the stack and none apart, the files) and its scene's contact count
against the same scene stepped by hand (an independent path: ``Bodies.step`` in a plain loop)."""

import json

import pytest

from torchdeform import cli


@pytest.mark.slow  # a bench smoke run (2-3 s on 2 cores)
def test_bench_bodies_quick_json(capsys, tmp_path):
    rc = cli.main(argv=["bench", "bodies", "--quick", "--json", "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    doc = json.loads(out)  # exactly one JSON document on stdout
    assert doc["bench"] == "bodies" and {"machine", "targets", "met"} <= set(doc)
    assert doc["targets"] == {"n": 24, "contact_ratio_max": 2.0} and doc["met"]["contact_ratio_24"] is None
    (row,) = doc["rows"]
    assert {"n", "steps_per_s_contact", "steps_per_s_apart", "contact_ratio", "contacts", "threads"} <= set(row)
    assert row["n"] == 16 and row["threads"] == 1 == doc["machine"]["threads"]
    assert row["steps_per_s_contact"] > 0 and row["steps_per_s_apart"] > 0
    assert row["contact_ratio"] == pytest.approx(row["steps_per_s_apart"] / row["steps_per_s_contact"])
    assert row["contacts"] > 0 and row["contacts_min"] > 0  # resting on the lower block
    assert row["contacts_apart"] == 0  # 1 m above it
    assert 0 < row["penetration_m"] < 0.01  # less than a spacing
    assert doc["met"]["contact"] is True
    assert (tmp_path / "bodies.csv").is_file() and (tmp_path / "bodies.png").is_file()


def test_bench_bodies_scene_contacts_by_hand():
    """The stack stepped by hand: the upper block rests on the lower one, both readings agree."""
    from torchdeform.bench.bodies import stacked_blocks

    n = 6
    scene, dt = stacked_blocks(n)
    states = scene.rest_states()
    for _ in range(60):
        states = scene.step(states, dt)
    contacts = int(states[0].readings["lower/upper.contacts"][0])
    assert contacts == int(states[1].readings["lower/upper.contacts"][0])
    # every node of the upper block's bottom layer over the lower's top ((n - 1)^2: the upper one is
    # shifted half a spacing) is pushed in by gravity each step; at most a layer of each body is in
    assert (n - 1) ** 2 <= contacts <= 2 * n * n
    apart, _ = stacked_blocks(n, apart=True)
    far = apart.step(apart.rest_states(), dt)
    assert int(far[0].readings["lower/upper.contacts"][0]) == 0


def test_bench_bodies_refuses_bad_sizes(capsys):
    assert cli.main(argv=["bench", "bodies", "--sizes", "2"]) == 2
    assert "--sizes" in capsys.readouterr().err

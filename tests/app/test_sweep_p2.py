"""`fem3d sweep` on quadratic (P2) bodies: a grid over E and the element itself (the bar of
tests/app/test_fit.py, 72 elements, 4 steps), each P2 case bit for bit what `fem3d run`
gives, its dataset holding every node (corner and edge nodes) of every frame."""

from __future__ import annotations

import csv

import numpy as np

from fem3d.app.fit.run import scene_toml
from fem3d.io.dataset import load_sweep, read_run_frames
from tests.app.test_fit import bar_scene
from tests.app.test_sweep_runs import _main


def test_sweep_over_E_and_the_element(tmp_path):
    scene = tmp_path / "bar.toml"
    scene.write_text(scene_toml(bar_scene(**{"bodies[0].element": "p2",
                                             "simulation.steps": 4})))
    spec = tmp_path / "s.toml"
    spec.write_text('scene = "bar.toml"\n[grid]\n"bodies[0].material.E" = [1e5, 3e5]\n'
                    '"bodies[0].element" = ["p1", "p2"]\n[dataset]\ndtype = "float64"\n')
    out = tmp_path / "out"
    rc, err = _main("sweep", str(spec), "--workers", "1", "--out", str(out), "--quiet")
    assert rc == 0, err
    assert "4 ok, 0 failed, 0 lost" in err, err
    with open(out / "results.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["bodies[0].element"] for r in rows] == ["p1", "p2"] * 2
    data = {case.id: case for case in load_sweep(out)}
    for r in rows:
        case = data[r["id"]]
        n = 175 if r["bodies[0].element"] == "p2" else 36  # P2: the 36 corners, 139 edge nodes
        assert case.positions.shape == (3, n, 3)  # frames 0, 2, 4
        assert case.positions.dtype == np.float64
    p2 = [r for r in rows if r["bodies[0].element"] == "p2"]
    assert p2[0]["total_final"] != p2[1]["total_final"]  # E reached the P2 cases
    for r in p2:
        alone = tmp_path / r["id"]
        rc, err = _main("run", str(scene), "--set",
                        f"bodies[0].material.E={r['bodies[0].material.E']}",
                        "--out", str(alone), "--no-preview", "--quiet")
        assert rc == 0, err
        case = out / "cases" / r["id"]
        for a, b in zip(read_run_frames(case), read_run_frames(alone), strict=True):
            np.testing.assert_array_equal(a, b)
        assert (case / "energy.csv").read_bytes() == (alone / "energy.csv").read_bytes()
        np.testing.assert_array_equal(data[r["id"]].positions, read_run_frames(alone)[2])

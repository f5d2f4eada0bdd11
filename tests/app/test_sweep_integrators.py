"""`fem3d sweep` over ``simulation.integrator``: each scheme runs as its own case (2 steps
of the armadillo's simulation mesh, pinned feet, scripted pull) and each case is what
`fem3d run` gives with that integrator."""

from __future__ import annotations

import csv
import json

import numpy as np

from fem3d.io.dataset import read_run_frames
from tests.app.test_sweep_runs import MESH, _main, _sweep_file

SCHEMES = ["linear", "implicit", "bdf2", "newmark", "static"]


def test_sweep_over_the_integrator(tmp_path):
    spec = _sweep_file(tmp_path, f"""
        [set]
        "simulation.steps" = 2
        [grid]
        "simulation.integrator" = {json.dumps(SCHEMES)}
    """)
    out = tmp_path / "out"
    rc, err = _main("sweep", str(spec), "--workers", "1", "--out", str(out), "--quiet")
    assert rc == 0, err
    assert f"{len(SCHEMES)} ok, 0 failed, 0 lost" in err, err
    with open(out / "results.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["simulation.integrator"] for r in rows] == SCHEMES
    assert all(r["status"] == "ok" and int(r["steps"]) == 2 for r in rows), rows
    finals = {r["simulation.integrator"]: float(r["total_final"]) for r in rows}
    assert len(set(finals.values())) == len(SCHEMES), finals  # five different schemes ran
    for r in rows:
        scene = json.loads((out / "cases" / r["id"] / "scene.json").read_text())
        assert scene["simulation"]["integrator"] == r["simulation.integrator"]
    newmark = next(r for r in rows if r["simulation.integrator"] == "newmark")
    alone = tmp_path / "alone"
    rc, err = _main("run", str(MESH), "--set", "simulation.steps=2", "--set",
                    "simulation.integrator=newmark", "--out", str(alone), "--no-preview",
                    "--quiet")
    assert rc == 0, err
    case = out / "cases" / newmark["id"]
    for a, b in zip(read_run_frames(case), read_run_frames(alone), strict=True):
        np.testing.assert_array_equal(a, b)
    assert (case / "energy.csv").read_bytes() == (alone / "energy.csv").read_bytes()

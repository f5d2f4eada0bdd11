"""Self-contact that matters: the folded strip (data/scenes/contact_fold.toml) intersects itself
without self-contact and never with it.

Both variants run through the CLI (`--set contact.self_contact=...`); every written frame is
checked by an independent test built from the frame's positions alone: a fresh
`ipctk.CollisionMesh` of the frame's surface triangles and `ipctk.has_intersections` (not
fem3d's ContactModel, whose contact set and filter are what is under test).
"""

from __future__ import annotations

from pathlib import Path

import ipctk
import meshio
import numpy as np
import pytest

from fem3d.app.cli import main

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "data" / "scenes" / "contact_fold.toml"
# the upper half is laid down by t = 1 s; without self-contact it sinks through the lower
# half from about step 88 on (measured), so 100 steps show it
STEPS = 100


def _intersecting_frames(out: Path) -> tuple[list[int], int, float]:
    """Indices of the frames whose surface intersects itself, the frame count, lowest y."""
    files = sorted((out / "frames").glob("frame_*.vtu"))
    first = meshio.read(files[0])
    faces = np.asarray(first.cells_dict["triangle"], dtype=np.int64)
    rest = np.asarray(first.points, dtype=float)
    mesh = ipctk.CollisionMesh(rest, ipctk.edges(faces), faces)  # one group: self-contact too
    bad, lowest = [], np.inf
    for i, f in enumerate(files):
        x = np.asarray(meshio.read(f).points, dtype=float)
        lowest = min(lowest, float(x[:, 1].min()))
        if ipctk.has_intersections(mesh, x):
            bad.append(i)
    return bad, len(files), lowest


def _run(tmp_path: Path, self_contact: bool, capsys) -> Path:
    out = tmp_path / f"fold_{self_contact}"
    status = main(["run", str(SCENE), "--steps", str(STEPS), "--out", str(out), "--quiet",
                   "--no-preview", "--set", f"contact.self_contact={str(self_contact).lower()}"])
    assert status == 0, capsys.readouterr().err
    return out


@pytest.fixture(scope="module")
def independent_check_works():
    """The check itself sees an intersection: two crossing triangles."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0],
                  [0.2, 0.2, -0.5], [0.2, 0.2, 0.5], [0.9, 0.9, 0.0]], dtype=float)
    F = np.array([[0, 1, 2], [3, 4, 5]])
    assert ipctk.has_intersections(ipctk.CollisionMesh(V, ipctk.edges(F), F), V)


def test_fold_intersects_without_self_contact_and_never_with_it(
        tmp_path, capsys, independent_check_works):
    bad_off, n_off, _ = _intersecting_frames(_run(tmp_path, False, capsys))
    assert n_off == STEPS + 1
    assert bad_off, "without self-contact the strip's halves should pass through each other"
    bad_on, n_on, lowest = _intersecting_frames(_run(tmp_path, True, capsys))
    assert n_on == STEPS + 1
    assert bad_on == [], f"frames {bad_on[:5]} intersect with self-contact on"
    assert lowest > 0.0  # and nothing below the ground

"""MEDIT ``TetrahedraP2`` files (meshio does not read them): read by fem3d's own MEDIT reader
into the same P2 mesh as a lifted linear mesh, refused with one line when broken."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.errors import InputError
from fem3d.mesh.quadratic import has_p2_cells, lift_to_p2, read_p2_mesh
from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.scene import load_scene
from fem3d.simulation import Simulation


def write_medit_p2(path: Path, X: np.ndarray, T: np.ndarray, *, extra: str = "",
                   comment: bool = False) -> Path:
    """A MEDIT file with ``X`` and 10-node tets ``T`` (0-based) in ``TetrahedraP2``."""
    lines = ["MeshVersionFormatted 2", "Dimension 3", "Vertices", str(len(X))]
    lines += [f"{x!r} {y!r} {z!r} 0" for x, y, z in X.tolist()]
    if comment:
        lines.insert(2, "# ten-node tets below")
    lines += ["TetrahedraP2", str(len(T))]
    lines += [" ".join(str(int(i) + 1) for i in row) + " 1" for row in T]
    path.write_text("\n".join(lines) + "\n" + extra + "End\n")
    return path


@pytest.fixture
def beam():
    X, T = box_tet_mesh((3, 1, 1), (1.0, 0.25, 0.25))
    X2, T2 = lift_to_p2(X, T)
    X2 = X2.copy()
    X2[T2[0, 4]] += [0.0, 0.01, 0.0]  # a curved element: the file's own edge node is kept
    return X2, T2


@pytest.mark.parametrize("comment", [False, True])  # the fast reader, the token reader
def test_tetrahedra_p2_read_as_written(beam, tmp_path, comment):
    X2, T2 = beam
    path = write_medit_p2(tmp_path / "beam.mesh", X2, T2, comment=comment)
    assert has_p2_cells(path)
    X, T = read_p2_mesh(path)
    assert np.array_equal(T, T2) and np.array_equal(X, X2)


def test_a_p2_scene_on_a_medit_p2_file(beam, tmp_path):
    X2, T2 = beam
    path = write_medit_p2(tmp_path / "beam.mesh", X2, T2)
    sim = Simulation(load_scene("cantilever", {"bodies[0].mesh": str(path),
                                               "bodies[0].element": "p2",
                                               "simulation.steps": 1}))
    assert np.array_equal(sim.model.T, T2) and np.array_equal(sim.model.X, X2)
    sim.step()
    assert np.isfinite(sim.q).all()
    # a linear MEDIT mesh is not taken for a quadratic one
    from fem3d.mesh.medit import write_medit

    X1, T1 = box_tet_mesh((3, 1, 1), (1.0, 0.25, 0.25))
    write_medit(tmp_path / "linear.mesh", X1, T1)
    assert not has_p2_cells(tmp_path / "linear.mesh")


def _one_line(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1, err
    return err[0]


def test_bad_tetrahedra_p2_files_are_one_line(beam, tmp_path, capsys):
    X2, T2 = beam
    good = write_medit_p2(tmp_path / "good.mesh", X2, T2)
    line = _one_line(capsys, ["run", "cantilever", "--set", f"bodies[0].mesh={str(good)!r}",
                              "--steps", "1", "--out", str(tmp_path / "o1"), "--quiet"])
    assert "bodies[0].element" in line and 'element = "p2"' in line
    assert line.count("bodies[0]") == 1 and line.count("cantilever.toml") == 1  # said once

    T_bad = T2.copy()
    T_bad[2, 7] = len(X2) + 5  # 1-based: len + 6
    bad = write_medit_p2(tmp_path / "bad.mesh", X2, T_bad)
    line = _one_line(capsys, ["run", "cantilever", "--set", f"bodies[0].mesh={str(bad)!r}",
                              "--set", 'bodies[0].element="p2"', "--steps", "1", "--out",
                              str(tmp_path / "o2"), "--quiet"])
    record_line = 4 + len(X2) + 2 + 3  # header, vertices, keyword and count, third record
    assert f"bad.mesh:{record_line}" in line and f"vertex {len(X2) + 6}" in line

    mixed = write_medit_p2(tmp_path / "mixed.mesh", X2, T2,
                           extra="Tetrahedra\n1\n1 2 3 4 0\n")
    with pytest.raises(InputError, match="mixes 4-node"):
        read_p2_mesh(mixed)
    short = tmp_path / "short.mesh"
    short.write_text(good.read_text().replace("TetrahedraP2\n" + str(len(T2)),
                                              "TetrahedraP2\n" + str(len(T2) + 1)))
    with pytest.raises(InputError) as info:
        read_p2_mesh(short)
    assert "\n" not in str(info.value)

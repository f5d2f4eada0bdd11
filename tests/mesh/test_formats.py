"""Reading, writing and checking meshes: the shipped data and round trips."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import meshio
import numpy as np
import pytest

from fem3d.errors import InputError  # noqa: E402
from fem3d.mesh.formats import (  # noqa: E402
    read_surface_mesh,
    read_tet_mesh,
    write_surface_mesh,
    write_tet_mesh,
)
from fem3d.mesh.skin import check_skin_inside  # noqa: E402
from fem3d.mesh.tetmesh import (  # noqa: E402
    MeshWarning,
    TetMesh,
    boundary_faces,
    tet_signed_volumes,
)
from tests.conftest_mesh_helpers import (  # noqa: E402
    DATA,
    ROOT,
    T2,
    X2,
    assert_valid_surface,
    assert_valid_tet_mesh,
    medit_text,
    obj_text,
    tetgen_texts,
)

SHIPPED_TET = [
    ("coarser_bunny.mesh", 500, 1518),
    ("coarse_bunny.mesh", 699, 2274),
    ("arma_6.node", 259, 627),
    ("arma_6.ele", 259, 627),
    ("arma_6", 259, 627),
]
SHIPPED_SURFACE = [
    ("armadillo.obj", 26002, 52000),
    ("coarser_bunny.obj", 251, 498),
    ("armadillo2.obj", 500, 834),
    ("bunny_skin.obj", 8786, 17568),
]


@pytest.fixture(scope="module")
def bunny() -> TetMesh:
    return read_tet_mesh(DATA / "coarser_bunny.mesh")


@pytest.fixture(scope="module")
def arma() -> TetMesh:
    return read_tet_mesh(DATA / "arma_6")


def closed_and_outward(X: np.ndarray, T: np.ndarray) -> None:
    F = boundary_faces(T)
    # closed 2-manifold: every undirected edge in exactly two faces, every directed edge once
    he = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    _, counts = np.unique(np.sort(he, axis=1), axis=0, return_counts=True)
    assert (counts == 2).all()
    _, dcounts = np.unique(he, axis=0, return_counts=True)
    assert (dcounts == 1).all(), "inconsistent face orientation"
    # outward: divergence theorem volume equals the sum of (positive) tet volumes
    a, b, c = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
    vol_surface = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
    vol_tets = tet_signed_volumes(X, T).sum()
    assert vol_tets > 0
    assert vol_surface == pytest.approx(vol_tets, rel=1e-10)


@pytest.mark.parametrize(("name", "n", "m"), SHIPPED_TET)
def test_shipped_tet_meshes(name: str, n: int, m: int) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)  # shipped meshes need no fixing
        mesh = read_tet_mesh(DATA / name)
    assert (mesh.n_vertices, mesh.n_tets) == (n, m)
    assert mesh.X.shape == (n, 3) and mesh.T.shape == (m, 4)
    assert_valid_tet_mesh(mesh)
    assert (mesh.volumes() > 0).all()
    assert mesh.path == str(DATA / name)
    closed_and_outward(np.asarray(mesh.X), np.asarray(mesh.T))


@pytest.mark.parametrize(("name", "n", "f"), SHIPPED_SURFACE)
def test_shipped_surface_meshes(name: str, n: int, f: int) -> None:
    V, F = read_surface_mesh(DATA / name)
    assert V.shape == (n, 3) and F.shape == (f, 3)
    assert_valid_surface(V, F)


def test_armadillo_obj_reader_returns_the_whole_mesh() -> None:
    """What the reader returns for the biggest shipped OBJ (its speed: bench/mesh_io.py)."""
    V, F = read_surface_mesh(DATA / "armadillo.obj")
    assert V.shape == (26002, 3) and F.shape == (52000, 3)
    assert V.dtype == np.float64 and np.issubdtype(F.dtype, np.integer)
    assert np.isfinite(V).all()
    assert F.min() == 0 and F.max() == 26001  # 0-based, every vertex used
    assert np.unique(F).size == 26002
    lines = (DATA / "armadillo.obj").read_text().splitlines()
    last_v = [ln for ln in lines if ln.startswith("v ")][-1]
    np.testing.assert_array_equal(V[-1], [float(x) for x in last_v.split()[1:4]])
    V2, F2 = read_surface_mesh(DATA / "armadillo.obj")
    assert np.array_equal(V, V2) and np.array_equal(F, F2)


def test_obj_first_values(bunny: TetMesh) -> None:
    V, F = read_surface_mesh(DATA / "armadillo.obj")
    np.testing.assert_array_equal(V[0], [0.079023, 0.815615, 0.046110])
    np.testing.assert_array_equal(F[0], [0, 1, 2])
    np.testing.assert_array_equal(F[-1], [13918, 14316, 13662])
    # the 500-vertex OBJ is the bunny sim mesh's boundary, same vertex order
    V2, F2 = read_surface_mesh(DATA / "armadillo2.obj")
    np.testing.assert_allclose(V2, bunny.X, rtol=0, atol=1e-9 * 200)
    key = lambda F: {tuple(sorted(f)) for f in F.tolist()}  # noqa: E731
    assert key(F2) == key(boundary_faces(bunny.T))


def test_medit_double_precision_and_meshio_agree(bunny: TetMesh) -> None:
    # own parser keeps all digits (meshio reads MeshVersionFormatted 1 as float32)
    assert bunny.X[4, 0] == -94.93529294134449
    m = meshio.read(DATA / "coarser_bunny.mesh")
    np.testing.assert_allclose(bunny.X, m.points, rtol=1e-6)
    np.testing.assert_array_equal(np.sort(bunny.T, 1), np.sort(m.cells_dict["tetra"], 1))


def test_tetgen_matches_file(arma: TetMesh) -> None:
    np.testing.assert_array_equal(arma.X[0], [0.0929169711709161, 0.8099746292063351,
                                              -0.0071472079391601])
    np.testing.assert_array_equal(arma.T[0], [60, 23, 27, 21])  # first column is the tet index
    np.testing.assert_array_equal(arma.T[-1], [1, 5, 2, 251])


def test_tetgen_one_based_detected(tmp_path: Path, arma: TetMesh) -> None:
    node, ele = tetgen_texts(arma.X, arma.T, base=1)
    assert node.splitlines()[1].startswith("1 ")
    (tmp_path / "one.node").write_text(node)
    (tmp_path / "one.ele").write_text(ele)
    (tmp_path / "zero.node").write_text(tetgen_texts(arma.X, arma.T, base=0)[0])
    (tmp_path / "zero.ele").write_text(tetgen_texts(arma.X, arma.T, base=0)[1])
    for stem in ("one", "zero"):
        m = read_tet_mesh(tmp_path / stem)
        np.testing.assert_array_equal(m.X, arma.X)
        np.testing.assert_array_equal(m.T, arma.T)


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".mesh", ".node", ".vtk"])
def test_round_trip(tmp_path: Path, bunny: TetMesh, suffix: str) -> None:
    path = tmp_path / f"bunny{suffix}"
    write_tet_mesh(path, bunny)
    back = read_tet_mesh(path)
    np.testing.assert_array_equal(back.X, bunny.X)  # all formats keep float64 digits
    np.testing.assert_array_equal(back.T, bunny.T)


def test_meshio_written_files_read(tmp_path: Path, arma: TetMesh) -> None:
    # files written by meshio itself (not by fem3d's writer), including gmsh 4.1
    for name, kw in [("a.msh", {"file_format": "gmsh"}), ("a.vtu", {}), ("b.mesh", {})]:
        meshio.write(tmp_path / name, meshio.Mesh(arma.X, [("tetra", arma.T)]), **kw)
        back = read_tet_mesh(tmp_path / name)
        np.testing.assert_allclose(back.X, arma.X, rtol=1e-6)
        np.testing.assert_array_equal(back.T, arma.T)


def test_boundary_faces_single_tet() -> None:
    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    F = boundary_faces(np.array([[0, 1, 2, 3]]))
    assert F.shape == (4, 3) and F.dtype == np.int64
    centroid = X.mean(0)
    n = np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]])
    assert (np.einsum("ij,ij->i", n, X[F].mean(1) - centroid) > 0).all()
    # shared face is interior
    F2 = boundary_faces(T2)
    assert F2.shape == (6, 3)
    assert {1, 2, 3} not in [set(f) for f in F2.tolist()]
    closed_and_outward(X2, T2)


def test_inverted_tets_reoriented_with_warning(tmp_path: Path) -> None:
    T = T2.copy()
    T[1] = T[1][[1, 0, 2, 3]]  # negatively oriented
    p = tmp_path / "inv.mesh"
    p.write_text(medit_text(X2, T))
    with pytest.warns(MeshWarning, match=r"re-oriented 1 of 2"):
        m = read_tet_mesh(p)
    assert_valid_tet_mesh(m)
    assert np.allclose(m.volumes(), tet_signed_volumes(X2, T2))


def test_unused_vertices_removed_with_warning(tmp_path: Path) -> None:
    X = np.vstack([X2, [[5.0, 5, 5]]])
    p = tmp_path / "extra.mesh"
    p.write_text(medit_text(X, T2))
    with pytest.warns(MeshWarning, match=r"removed 1 vertices"):
        m = read_tet_mesh(p)
    assert m.n_vertices == 5
    np.testing.assert_array_equal(m.T, T2)


def test_tetmesh_is_immutable(bunny: TetMesh) -> None:
    with pytest.raises(ValueError):
        bunny.X[0, 0] = 1.0
    with pytest.raises(AttributeError):
        bunny.X = np.zeros((1, 3))  # type: ignore[misc]


def test_obj_forms(tmp_path: Path) -> None:
    text = """# every face form OBJ allows
o thing
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0 0
vn 0 0 1
  v 0 0 1 0.5 0.5 0.5
f 1/1/1 2/1/1 3/1/1
f 1//1 3//1 4//1
f 1/1 2/1 5/1
f -5 -3 -1
f 1 2 3 4
s off
usemtl x
l 1 2
"""
    p = tmp_path / "forms.obj"
    p.write_text(text)
    V, F = read_surface_mesh(p)
    assert V.shape == (5, 3)
    np.testing.assert_array_equal(
        F, [[0, 1, 2], [0, 2, 3], [0, 1, 4], [0, 2, 4], [0, 1, 2], [0, 2, 3]]
    )


def test_surface_via_meshio_and_tets(tmp_path: Path, arma: TetMesh) -> None:
    V, F = read_surface_mesh(DATA / "armadillo2.obj")
    write_surface_mesh(tmp_path / "s.stl", V, F)
    V2, F2 = read_surface_mesh(tmp_path / "s.stl")
    assert F2.shape == F.shape
    write_surface_mesh(tmp_path / "s.obj", V, F)
    V3, F3 = read_surface_mesh(tmp_path / "s.obj")
    np.testing.assert_allclose(V3, V, rtol=1e-8)
    np.testing.assert_array_equal(F3, F)
    # a tet mesh as a display mesh: its boundary
    write_tet_mesh(tmp_path / "a.vtu", arma)
    V4, F4 = read_surface_mesh(tmp_path / "a.vtu")
    assert F4.shape == (500, 3)
    assert_valid_surface(V4, F4)


def test_check_skin_inside(arma: TetMesh, bunny: TetMesh) -> None:
    V, _ = read_surface_mesh(DATA / "armadillo.obj")
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)
        d = check_skin_inside(V, arma.X, T=arma.T)  # a few vertices just outside: fine
        assert 0 < d.max() < 0.05 * np.linalg.norm(np.ptp(arma.X, 0))
        check_skin_inside(V, arma.X)
    moved = V.copy()
    moved[:10] += [0.0, 2.0, 0.0]  # 10 vertices far above the armadillo
    with pytest.warns(MeshWarning, match=r"10 of 26002 vertices") as rec:
        check_skin_inside(moved, arma.X, T=arma.T)
    assert "max 1." in str(rec[0].message)
    with pytest.warns(MeshWarning, match=r"10 of 26002"):
        check_skin_inside(moved, arma.X)  # bounding box only
    # the shipped bunny skin lies inside the bunny simulation mesh
    S, _ = read_surface_mesh(DATA / "bunny_skin.obj")
    d = check_skin_inside(S, bunny.X, T=bunny.T)
    assert d.max() == 0.0


def test_bunny_skin_up_to_date(tmp_path: Path) -> None:
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import make_bunny_skin
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    out = tmp_path / "skin.obj"
    make_bunny_skin.main(["--out", str(out)])
    assert out.read_bytes() == (DATA / "bunny_skin.obj").read_bytes(), (
        "data/bunny_skin.obj is stale: run `python scripts/make_bunny_skin.py`"
    )
    V, F = read_surface_mesh(out)
    he = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    _, dcounts = np.unique(he, axis=0, return_counts=True)
    assert (dcounts == 1).all() and len(dcounts) == 3 * len(F)  # closed, consistently oriented
    vol = np.einsum("ij,ij->", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])) / 6
    assert vol > 0  # outward


def test_input_error_is_raised_for_directory(tmp_path: Path) -> None:
    (tmp_path / "d.mesh").mkdir()
    with pytest.raises(InputError, match="directory"):
        read_tet_mesh(tmp_path / "d.mesh")


def test_obj_text_helper_round_trip(tmp_path: Path) -> None:
    p = tmp_path / "h.obj"
    F = boundary_faces(T2)
    p.write_text(obj_text(X2, F))
    V, F2 = read_surface_mesh(p)
    np.testing.assert_array_equal(V, X2)
    np.testing.assert_array_equal(F2, F)


def test_medit_as_display_mesh(tmp_path: Path) -> None:
    # tets only: the boundary surface
    p = tmp_path / "tets.mesh"
    p.write_text(medit_text(X2, T2))
    V, F = read_surface_mesh(p)
    assert V.shape == (5, 3) and F.shape == (6, 3)
    # explicit Triangles and Quadrilaterals (quads split in two)
    text = medit_text(X2, T2).replace(
        "Tetrahedra", "Triangles\n1\n1 2 3 7\nQuadrilaterals\n1\n1 2 5 3 0\nTetrahedra", 1
    )
    p.write_text(text)
    V, F = read_surface_mesh(p)
    np.testing.assert_array_equal(F, [[0, 1, 2], [0, 1, 4], [0, 4, 2]])


def test_box_tet_mesh_is_conforming_positive_and_fills_the_box() -> None:
    from fem3d.mesh.tetmesh import boundary_faces, box_tet_mesh

    X, T = box_tet_mesh((3, 2, 4), (0.3, 0.2, 0.8), origin=(1.0, -1.0, 0.5))
    assert X.shape == (4 * 3 * 5, 3) and T.shape == (6 * 3 * 2 * 4, 4)
    e = X[T[:, 1:]] - X[T[:, :1]]
    vol = np.linalg.det(e) / 6.0
    assert (vol > 0).all()
    np.testing.assert_allclose(vol.sum(), 0.3 * 0.2 * 0.8, rtol=1e-12)
    np.testing.assert_allclose(X.min(axis=0), [1.0, -1.0, 0.5])
    # conforming: only the box's outer faces are boundary faces (2 triangles per cell face)
    assert len(boundary_faces(T)) == 2 * 2 * (3 * 2 + 2 * 4 + 3 * 4)

"""The element objects (fem3d.mesh.element), P2 lifting and reading (fem3d.mesh.quadratic),
the node-count-free sparsity pattern and skinning, and ``bodies[].element`` in scenes."""

from __future__ import annotations

import itertools

import meshio
import numpy as np
import pytest
import scipy.sparse as sp

from fem3d.errors import InputError
from fem3d.mesh.element import ELEMENTS, TET_EDGES, MixedElementError, element
from fem3d.mesh.quadratic import lift_to_p2, read_p2_mesh, write_element_mesh
from fem3d.mesh.skin import build_skinning_matrix
from fem3d.mesh.tetmesh import boundary_faces, box_tet_mesh
from fem3d.physics.pattern import block_pattern

P1, P2 = ELEMENTS["p1"], ELEMENTS["p2"]


def _quadratic(x: np.ndarray) -> np.ndarray:
    """A full quadratic map R^3 -> R^3 (every monomial of degree <= 2)."""
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    return np.stack([1 + 2 * x0 - x1 + 3 * x0 * x1 - x2 ** 2 + 0.5 * x0 ** 2,
                     x1 + x1 * x2 - 2 * x0 * x2 + x1 ** 2,
                     -0.5 + x2 + 0.7 * x0 ** 2 - x0 * x1 + 2 * x2 * x1], axis=-1)


def test_registry():
    assert element("p1") is P1 and element(P2) is P2
    assert (P1.n_nodes, P1.n_dofs, P1.cell_type, P1.vtk_type) == (4, 12, "tetra", 10)
    assert (P2.n_nodes, P2.n_dofs, P2.cell_type, P2.vtk_type) == (10, 30, "tetra10", 24)
    with pytest.raises(ValueError, match="unknown element 'p7'; available: p1, p2"):
        element("p7")


def test_p1_faces_are_the_mesh_boundary():
    X, T = box_tet_mesh((3, 2, 2))
    assert np.array_equal(P1.boundary_faces(T), boundary_faces(T))
    assert np.array_equal(P1.surface_triangles(T), boundary_faces(T))
    assert P1.element_dofs(T).shape == (T.shape[0], 12)


def test_lift_shares_edges_once():
    X, T = box_tet_mesh((2, 3, 2), size=(1.0, 2.0, 0.5))
    X2, T2 = lift_to_p2(X, T)
    edges = {tuple(sorted(e)) for t in T for e in itertools.combinations(t.tolist(), 2)}
    assert X2.shape[0] == X.shape[0] + len(edges)
    assert np.array_equal(T2[:, :4], T)
    # every edge node is its edge's midpoint, and one edge has one node
    mid = 0.5 * (X[T[:, TET_EDGES[:, 0]]] + X[T[:, TET_EDGES[:, 1]]])
    assert np.array_equal(X2[T2[:, 4:]], mid)
    assert np.unique(X2, axis=0).shape[0] == X2.shape[0]
    assert np.unique(T2).size == X2.shape[0]  # every node used


def test_p2_surface_is_the_p1_surface_split_in_four():
    X, T = box_tet_mesh((2, 2, 3), size=(1.0, 1.5, 2.0))
    X2, T2 = lift_to_p2(X, T)
    faces = P2.boundary_faces(T2)
    F1 = boundary_faces(T)
    assert np.array_equal(faces[:, :3], F1)
    tris = P2.surface_triangles(T2)
    assert tris.shape == (4 * F1.shape[0], 3)
    # a closed, outward surface: the divergence theorem gives the box's volume
    a, b, c = X2[tris[:, 0]], X2[tris[:, 1]], X2[tris[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    assert volume == pytest.approx(3.0, rel=1e-12)
    # each edge of the split surface is shared by exactly two triangles
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert (counts == 2).all()


def test_p2_shape_functions_reproduce_quadratics():
    rng = np.random.default_rng(3)
    X, T = box_tet_mesh((1, 1, 1))
    X2, T2 = lift_to_p2(X + 0.1 * rng.standard_normal(X.shape), T)
    lam = rng.dirichlet(np.ones(4), size=50)
    e = rng.integers(0, T2.shape[0], size=50)
    p = np.einsum("ka,kai->ki", lam, X2[T2[e, :4]])
    N = P2.shape_values(lam)
    assert np.allclose(N.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    values = np.einsum("ka,kai->ki", N, _quadratic(X2)[T2[e]])
    assert np.allclose(values, _quadratic(p), rtol=0, atol=1e-12)
    # P1 cannot: its interpolation of the same field misses by O(h^2)
    linear = np.einsum("ka,kai->ki", P1.shape_values(lam), _quadratic(X2)[T2[e, :4]])
    assert np.abs(linear - _quadratic(p)).max() > 1e-3


def test_p2_skinning_carries_quadratic_motion():
    X, T = box_tet_mesh((2, 2, 2))
    X2, T2 = lift_to_p2(X, T)
    rng = np.random.default_rng(5)
    skin = rng.uniform(0.02, 0.98, size=(200, 3))
    W = build_skinning_matrix(X2, T2, skin, element=P2)
    assert W.shape == (200, X2.shape[0]) and (np.diff(W.indptr) <= 10).all()
    assert np.allclose(W @ _quadratic(X2), _quadratic(skin), rtol=0, atol=1e-12)
    W1 = build_skinning_matrix(X, T, skin)
    assert np.abs(W1 @ _quadratic(X) - _quadratic(skin)).max() > 1e-3
    with pytest.raises(InputError, match=r"shape \(m, 10\)"):
        build_skinning_matrix(X, T, skin, element=P2)


@pytest.mark.parametrize("cells", [(1, 1, 1), (2, 1, 3)])
def test_pattern_of_ten_node_elements(cells):
    X, T = box_tet_mesh(cells)
    X2, T2 = lift_to_p2(X, T)
    n = X2.shape[0]
    pattern, scatter = block_pattern(T2, n)
    assert scatter.size == T2.shape[0] * 900
    rng = np.random.default_rng(1)
    blocks = rng.standard_normal((T2.shape[0], 30, 30))
    data = np.bincount(scatter, weights=blocks.reshape(-1), minlength=pattern.nnz)
    dofs = P2.element_dofs(T2)
    rows = np.repeat(dofs, 30, axis=1).reshape(-1)
    cols = np.tile(dofs, (1, 30)).reshape(-1)
    ref = sp.coo_matrix((blocks.reshape(-1), (rows, cols)), shape=(3 * n, 3 * n)).toarray()
    A = sp.csr_matrix((data, pattern.indices, pattern.indptr), shape=pattern.shape)
    assert np.allclose(A.toarray(), ref, rtol=0, atol=1e-12)
    assert pattern.nnz == np.count_nonzero(ref)


@pytest.mark.parametrize("suffix", [".vtu", ".msh"])
def test_read_ten_node_tets(tmp_path, suffix):
    X, T = box_tet_mesh((2, 1, 1))
    X2, T2 = lift_to_p2(X, T)
    path = tmp_path / f"beam{suffix}"
    kwargs = {"file_format": "gmsh22", "binary": False} if suffix == ".msh" else {}
    meshio.write(path, meshio.Mesh(X2, [("tetra10", T2)]), **kwargs)
    Xr, Tr = read_p2_mesh(path)
    assert np.array_equal(Xr[Tr], X2[T2])  # the same nodes in the same local order


def test_read_refuses_non_conforming_and_linear(tmp_path):
    X, T = box_tet_mesh((2, 1, 1))
    X2, T2 = lift_to_p2(X, T)
    bad = T2.copy()
    extra = X2.shape[0]
    bad[0, 4] = extra  # tet 0 gets its own node on an edge its neighbours share
    Xb = np.concatenate([X2, X2[T2[0, 4]][None]])
    path = tmp_path / "bad.vtu"
    meshio.write(path, meshio.Mesh(Xb, [("tetra10", bad)]))
    shared = (np.sort(T2[:, 4:], axis=None)[1:] == np.sort(T2[:, 4:], axis=None)[:-1]).any()
    assert shared
    with pytest.raises(InputError, match="edge node that a neighbour"):
        read_p2_mesh(path)
    linear = tmp_path / "linear.vtu"
    meshio.write(linear, meshio.Mesh(X, [("tetra", T)]))
    with pytest.raises(InputError, match="no 10-node"):
        read_p2_mesh(linear)


def test_write_quadratic_vtu(tmp_path):
    X, T = box_tet_mesh((1, 2, 1))
    X2, T2 = lift_to_p2(X, T)
    path = tmp_path / "p2.vtu"
    write_element_mesh(path, X2 * 2.0, T2, P2, {"u": X2})
    mesh = meshio.read(path)
    assert [c.type for c in mesh.cells] == ["tetra10"]  # VTK type 24, quadratic tetra
    assert len(mesh.cells[0].data) == 12 and np.array_equal(mesh.point_data["u"], X2)
    Xr, Tr = read_p2_mesh(path)
    assert np.array_equal(Xr[Tr], 2.0 * X2[T2])


def _scene(tmp_path, mesh: str, element: str | None, second: str | None = None) -> str:
    body = 'mesh = "{}"\nmaterial = {{ E = 1e5, nu = 0.3, density = 1000.0 }}\n'
    text = "[simulation]\nsteps = 1\n\n[[bodies]]\n" + body.format(mesh)
    if element is not None:
        text += f'element = "{element}"\n'
    if second is not None:
        text += "\n[[bodies]]\n" + body.format(mesh) + f'element = "{second}"\n'
        text += "transform = { translate = [3.0, 0.0, 0.0] }\n"
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return str(path)


def test_scene_element_key(tmp_path):
    from fem3d.mesh.formats import write_tet_mesh
    from fem3d.mesh.tetmesh import TetMesh
    from fem3d.scene import load_scene
    from fem3d.scene.arrays import build_arrays

    X, T = box_tet_mesh((2, 1, 1))
    write_tet_mesh(tmp_path / "box.mesh", TetMesh(X, T))
    a = build_arrays(load_scene(_scene(tmp_path, "box.mesh", None)))
    assert a.element is P1 and a.T.shape == T.shape
    a = build_arrays(load_scene(_scene(tmp_path, "box.mesh", "p2")))
    X2, T2 = lift_to_p2(X, T)
    assert a.element is P2 and np.array_equal(a.T, T2) and np.array_equal(a.X, X2)
    with pytest.raises(InputError, match=r"bodies\[0\]\.element.*p1.*p2"):
        load_scene(_scene(tmp_path, "box.mesh", "p3"))
    # bodies may mix elements: one element block per run of bodies (the P2 body's nodes
    # first), the scene's T and element standing in for "no single one"
    a = build_arrays(load_scene(_scene(tmp_path, "box.mesh", "p2", "p1")))
    assert [b.element for b in a.blocks] == [P2, P1] and a.is_mixed
    assert np.array_equal(a.blocks[0].T, T2) and np.array_equal(a.blocks[1].T, T + len(X2))
    assert [(b.tets.start, b.tets.stop) for b in a.blocks] == [(0, len(T)), (len(T), 2 * len(T))]
    with pytest.raises(MixedElementError, match=r"arrays\.T: the bodies mix elements"):
        print(a.T.shape)
    write_element_mesh(tmp_path / "box10.vtu", X2, T2, P2)
    with pytest.raises(InputError, match=r'bodies\[0\]\.element: box10.vtu has 10-node '
                                         r'\(quadratic\) tets: set element = "p2"'):
        build_arrays(load_scene(_scene(tmp_path, "box10.vtu", None)))
    a = build_arrays(load_scene(_scene(tmp_path, "box10.vtu", "p2")))
    assert np.array_equal(a.X[a.T], X2[T2])

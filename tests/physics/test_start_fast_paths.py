"""The fast paths of a run's start (issue 23) give what the plain algorithms give.

Each fast path is checked against the straightforward computation it replaced (a global
``np.unique`` of the vertex pairs, one ``np.bincount`` of every element block, the token
reader of MEDIT files, ``np.unique`` over tets and faces), on a shuffled mesh so that no
ordering of a generated box is relied on; and ``fem3d run --profile`` prints its stages.
"""

from __future__ import annotations

import warnings
from functools import partial

import numpy as np
import pytest
import scipy.sparse as sp

from fem3d.app.cli import main
from fem3d.errors import InputError
from fem3d.kernels.dispatch import geometry_kernels
from fem3d.mesh import medit, textscan
from fem3d.mesh.element import element
from fem3d.mesh.formats import read_tet_mesh, write_tet_mesh
from fem3d.mesh.tetmesh import TetMesh, boundary_faces, box_tet_mesh, validate_tet_mesh
from fem3d.physics import pattern as pattern_module
from fem3d.physics.model import block_pattern, build_model, element_dofs


@pytest.fixture(scope="module")
def shuffled_box():
    X, T = box_tet_mesh((5, 4, 3), size=(1.0, 0.8, 0.6))
    rng = np.random.default_rng(7)
    perm = rng.permutation(len(X))
    inverse = np.argsort(perm)
    return X[perm], inverse[T][rng.permutation(len(T))]


def test_block_pattern_matches_the_assembled_csr(shuffled_box):
    X, T = shuffled_box
    n = len(X)
    pattern, scatter = block_pattern(T, n)
    dofs = element_dofs(T)
    rows = np.repeat(dofs[:, :, None], 12, axis=2).reshape(-1)
    cols = np.repeat(dofs[:, None, :], 12, axis=1).reshape(-1)
    # the reference: COO -> CSR of random blocks; the pattern holds every (row, col) pair
    rng = np.random.default_rng(0)
    blocks = rng.random(T.shape[0] * 144)
    ref = sp.coo_matrix((blocks, (rows, cols)), shape=(3 * n, 3 * n)).tocsr()
    ref.sort_indices()
    assert np.array_equal(pattern.indptr, ref.indptr)
    assert np.array_equal(pattern.indices, ref.indices)
    assert scatter.dtype == np.int32 and pattern.indices.dtype == np.int32
    # every element entry lands on its own (row, col)
    row_of = np.repeat(np.arange(3 * n), np.diff(pattern.indptr))
    assert np.array_equal(row_of[scatter], rows)
    assert np.array_equal(pattern.indices[scatter], cols)
    assert np.allclose(np.bincount(scatter, blocks, minlength=pattern.nnz), ref.data)


@pytest.mark.parametrize("per_tet_density", [False, True])
def test_mass_matrix_is_the_bincount_of_every_block_bit_for_bit(shuffled_box, per_tet_density,
                                                                 monkeypatch):
    X, T = shuffled_box
    density = np.linspace(500.0, 1500.0, len(T)) if per_tet_density else 1000.0
    monkeypatch.setattr(pattern_module, "_MASS_CHUNK", 37)  # several uneven chunks
    model = build_model(X, T, E=1e5, nu=0.3, density=density, backend="numpy")
    geo = geometry_kernels(backend="numpy")
    blocks = geo.mass_matrix(model.vol * density, (1.0,)) if per_tet_density else \
        geo.mass_matrix(model.vol, (1000.0,))
    ref = np.bincount(model.scatter, weights=blocks.reshape(-1), minlength=model.nnz)
    assert model.mass.data.tobytes() == ref.tobytes()
    # the entry-by-entry path (blocks of any structure) gives the same sums
    element_mass = partial(element("p1").mass_matrices, geo, model.X, model.T, model.vol,
                           1000.0, density if per_tet_density else None)
    entries = pattern_module._assemble_entries(element_mass, len(model.T), model.scatter,
                                               model.nnz)
    ref_entries = ref if not per_tet_density else np.bincount(
        model.scatter, weights=geo.mass_matrix(model.vol * density, (1.0,)).reshape(-1),
        minlength=model.nnz)
    assert entries.tobytes() == ref_entries.tobytes()


@pytest.mark.parametrize("chunk", [None, 61])  # one block; many, cut at uneven line ends
def test_plain_medit_reader_gives_the_token_readers_arrays(tmp_path, shuffled_box, chunk,
                                                           monkeypatch):
    X, T = shuffled_box
    path = tmp_path / "box.mesh"
    write_tet_mesh(path, TetMesh(X, T))
    if chunk is not None:
        monkeypatch.setattr(medit, "_PARSE_CHUNK", chunk)
    text = path.read_text()
    plain = medit._read_medit_plain(path, path.read_bytes())
    tokens = medit._read_medit_tokens(path, textscan.Tokens(path, text=text,
                                                            keywords=medit.MEDIT_KEYWORDS))
    assert plain.keys() == tokens.keys()
    for key, (values, lines) in plain.items():
        assert values.dtype == tokens[key][0].dtype
        assert values.tobytes() == tokens[key][0].tobytes()
        assert [lines[i] for i in (0, len(values) - 1)] == \
            [tokens[key][1][0], tokens[key][1][-1]]


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace("Vertices", "# a comment\nVertices"), None),  # token reader, same mesh
    (lambda t: t.replace("Tetrahedra\n", "Tetrahedra\n  "), None),
    (lambda t: t.replace(" 1 1 0\n", " 1.5e0 1 0\n", 1), None),
    (lambda t: t.rsplit("End", 1)[0], "file ends without the 'End' keyword"),
    (lambda t: t.replace("\nEnd", " 7\nEnd"), "expected a keyword, found the number '7'"),
    # white space alone where a record should be (NumPy's parser makes a number of it)
    (lambda t: t.replace("\nEnd", "\nCorners\n1\n \nEnd"),
     "Corners section declares 1 entries but keyword .End. comes after 0"),
    # a count no memory holds: refused before anything is allocated for it
    (lambda t: t.replace("Vertices\n8\n", "Vertices\n8000000000\n"),
     "Vertices section declares 8000000000 entries but keyword 'Tetrahedra' comes after 8"),
])
def test_medit_files_the_plain_reader_leaves_to_the_token_reader(tmp_path, edit, message):
    X, T = box_tet_mesh((1, 1, 1))
    good = tmp_path / "good.mesh"
    write_tet_mesh(good, TetMesh(X, T))
    path = tmp_path / "edited.mesh"
    path.write_text(edit(good.read_text()))
    if message is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert read_tet_mesh(path).T.shape == (6, 4)
    else:
        with pytest.raises(InputError, match=message) as err:
            read_tet_mesh(path)
        assert "edited.mesh:" in str(err.value)


def test_repeated_tet_and_overshared_face_on_a_large_numbering():
    # more than 55,000 vertices: the duplicate check hashes tets instead of packing them
    X, T = box_tet_mesh((2, 2, 2))
    filler = len(X) + np.arange(60_000).reshape(-1, 4)  # 15,000 separate unit tets
    corner = np.random.default_rng(1).random((len(filler), 3)) * 100.0 + 5.0
    Xf = np.concatenate([X, np.zeros((filler.size, 3))])
    for k, offset in enumerate(np.vstack([np.zeros(3), np.eye(3)])):
        Xf[filler[:, k]] = corner + offset
    Tf = np.concatenate([T, filler])
    assert validate_tet_mesh(Xf, Tf).n_tets == len(Tf)
    with pytest.raises(InputError, match=r"tet \d+ duplicates tet 3 "):
        validate_tet_mesh(Xf, np.concatenate([Tf, Tf[3:4, [1, 0, 3, 2]]]))
    faces = np.sort(T[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
    shared, counts = np.unique(faces, axis=0, return_counts=True)
    third = np.array([[*shared[np.argmax(counts == 2)], filler[0, 0]]])  # on an inner face
    with pytest.raises(InputError, match="already share"):
        validate_tet_mesh(Xf, np.concatenate([Tf, third]), path="m.mesh")


def test_boundary_faces_are_the_faces_one_tet_has(shuffled_box):
    _, T = shuffled_box
    faces = T[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True,
                                   return_counts=True)
    assert np.array_equal(boundary_faces(T), faces[counts[inverse.reshape(-1)] == 1])


def test_run_profile_prints_each_stage(tmp_path, capsys):
    mesh = tmp_path / "bar.mesh"  # a file of its own: no earlier test has read it (cached)
    write_tet_mesh(mesh, TetMesh(*box_tet_mesh((6, 2, 2), size=(3.0, 1.0, 1.0))))
    status = main(["run", str(mesh), "--steps", "1", "--out", str(tmp_path / "o"),
                   "--quiet", "--no-preview", "--profile", "--linear-solver", "amg"])
    assert status == 0
    err = capsys.readouterr().err
    table = err.split("fem3d run --profile:\n", 1)[1].splitlines()
    stages = [line.split("  ")[0] for line in table[1:]]
    for stage in ("start-up (Python, imports)", "read mesh", "validate mesh",
                  "model: sparsity pattern", "model: mass matrix", "system: reduced pattern",
                  "system: amg analysis", "first step", "time to first step"):
        assert stage in stages, (stage, table)
    first = float(table[-1].split()[4])
    assert first > 0


def test_token_spans_are_str_split_with_line_numbers():
    text = "  a 1\t2\r\n\n\x0b3  4.5e-3\x1c x\n\ty  \n-7"
    spans = textscan.TokenSpans(text)
    assert spans[:] == text.split() and [spans[i] for i in range(len(spans))] == text.split()
    lines = [i + 1 for i, ln in enumerate(text.split("\n")) for _ in ln.split()]
    assert spans.line.tolist() == lines and spans.n_lines == text.count("\n") + 1
    assert spans.values(2, 4, np.float64).tolist() == [2.0, 3.0]
    assert spans.values(0, 2, np.float64) is None  # 'a' is no number

"""Bad mesh files: every reader raises InputError naming the file and line / element.

One test per kind of bad input, then a hypothesis property test: random bytes and randomly
corrupted shipped meshes fed to every reader yield InputError or a fully valid mesh, never
another exception and never a half-read mesh.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fem3d.errors import InputError  # noqa: E402
from fem3d.mesh.formats import (  # noqa: E402
    read_surface_mesh,
    read_tet_mesh,
    write_surface_mesh,
    write_tet_mesh,
)
from fem3d.mesh.tetmesh import MeshWarning, TetMesh  # noqa: E402
from tests.conftest_mesh_helpers import (  # noqa: E402
    DATA,
    T2,
    X2,
    assert_valid_surface,
    assert_valid_tet_mesh,
    medit_text,
    obj_text,
    tetgen_texts,
)

F2 = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # one tet's surface


def raises_at(
    reader: Callable, path: Path, match: str, *, line: int | None = None,
    element: int | None = None,
) -> InputError:
    """Call ``reader(path)``, expect InputError naming the file, line / element, reason."""
    with pytest.raises(InputError) as info:
        reader(path)
    err = info.value
    msg = str(err)
    assert path.name in msg, msg
    assert re.search(match, msg, flags=re.IGNORECASE), msg
    if line is not None:
        assert err.line == line, msg
        assert f"{path.name}:{line}" in msg, msg
    if element is not None:
        assert err.element == element, msg
        assert f"element {element}" in msg, msg
    return err


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def write_tetgen(tmp_path: Path, node: str, ele: str, stem: str = "m") -> Path:
    (tmp_path / f"{stem}.node").write_text(node)
    (tmp_path / f"{stem}.ele").write_text(ele)
    return tmp_path / f"{stem}.ele"


def medit_lines(**kw) -> list[str]:
    return medit_text(X2, T2, **kw).split("\n")


# line numbers in medit_text(X2, T2): 1 version, 2 dim, 3 Vertices, 4 count, 5-9 vertices,
# 10 Tetrahedra, 11 count, 12-13 tets, 14 End
# tetgen_texts(X2, T2): .node line 1 header, 2-6 vertices; .ele line 1 header, 2-3 tets


# ------------------------------------------------------------------------ missing / unknown


def test_missing_file(tmp_path: Path) -> None:
    raises_at(read_tet_mesh, tmp_path / "nope.mesh", "not found")
    raises_at(read_tet_mesh, tmp_path / "nope.vtu", "not found")
    raises_at(read_surface_mesh, tmp_path / "nope.obj", "not found")
    # TetGen pair with the .ele missing
    (tmp_path / "half.node").write_text(tetgen_texts(X2, T2)[0])
    raises_at(read_tet_mesh, tmp_path / "half.node", "not found.*half.ele")
    raises_at(read_tet_mesh, tmp_path / "half", "not found")


def test_unknown_extension(tmp_path: Path) -> None:
    p = write(tmp_path / "m.xyz", medit_text(X2, T2))
    raises_at(read_tet_mesh, p, r"unknown tet-mesh file extension '\.xyz'")
    raises_at(read_surface_mesh, p, r"unknown surface-mesh file extension '\.xyz'")
    raises_at(read_tet_mesh, write(tmp_path / "s.obj", obj_text(X2, F2)), "unknown tet-mesh")


# ------------------------------------------------------------------------ empty / truncated


@pytest.mark.parametrize("name", ["e.mesh", "e.node", "e.vtu", "e.msh", "e.obj", "e.stl"])
def test_empty_file(tmp_path: Path, name: str) -> None:
    p = write(tmp_path / name, "" if name != "e.msh" else "\n  \n")
    if name == "e.node":
        (tmp_path / "e.ele").write_text(tetgen_texts(X2, T2)[1])
    reader = read_surface_mesh if name.endswith((".obj", ".stl")) else read_tet_mesh
    raises_at(reader, p, "empty file")


def test_truncated_medit(tmp_path: Path) -> None:
    text = medit_text(X2, T2)
    p = write(tmp_path / "cut.mesh", text[: text.index("2 5 3 4 0") + 5])  # mid last tet
    raises_at(read_tet_mesh, p, r"truncated.*Tetrahedra.*2 entries.*only 1", line=13)
    # cut at the end of a line: the End keyword is missing
    p = write(tmp_path / "noend.mesh", text[: text.index("End")])
    raises_at(read_tet_mesh, p, r"without the 'End'.*truncated", line=14)


def test_truncated_tetgen(tmp_path: Path) -> None:
    node, ele = tetgen_texts(X2, T2)
    p = write_tetgen(tmp_path, node, ele[:-5])
    raises_at(read_tet_mesh, p, r"truncated.*tetrahedron.*2 entries", line=3)
    p = write_tetgen(tmp_path, node[: node.rindex("\n4 ")], ele, stem="n")
    raises_at(read_tet_mesh, tmp_path / "n.node", r"truncated.*node.*5 entries.*only 4", line=5)


def test_truncated_obj_and_binary(tmp_path: Path) -> None:
    text = obj_text(X2, F2)
    p = write(tmp_path / "cut.obj", text[: text.rindex(" ")])
    raises_at(read_surface_mesh, p, r"face needs at least 3 vertices", line=9, element=3)
    # a truncated .vtu (meshio's error becomes an InputError)
    mesh = TetMesh(X2, T2)
    write_tet_mesh(tmp_path / "full.vtu", mesh)
    data = (tmp_path / "full.vtu").read_bytes()
    (tmp_path / "cut.vtu").write_bytes(data[: len(data) // 2])
    raises_at(read_tet_mesh, tmp_path / "cut.vtu", "not a readable VTU file")
    write_tet_mesh(tmp_path / "full.msh", mesh)
    data = (tmp_path / "full.msh").read_bytes()
    (tmp_path / "cut.msh").write_bytes(data[: len(data) // 2])
    raises_at(read_tet_mesh, tmp_path / "cut.msh", "not a readable MSH file")


# ------------------------------------------------------------------------ wrong counts


def test_wrong_counts_medit(tmp_path: Path) -> None:
    lines = medit_lines()
    lines[3] = "6"  # 5 vertices follow
    p = write(tmp_path / "more.mesh", "\n".join(lines))
    raises_at(read_tet_mesh, p, r"Vertices section declares 6 entries but keyword 'Tetrahedra'",
              line=10)
    lines[3] = "4"
    p = write(tmp_path / "fewer.mesh", "\n".join(lines))
    raises_at(read_tet_mesh, p, r"expected a keyword, found the number.*count of the Vertices",
              line=9)
    lines = medit_lines()
    lines[10] = "3"  # 2 tets follow
    p = write(tmp_path / "tets.mesh", "\n".join(lines))
    raises_at(read_tet_mesh, p, r"Tetrahedra section declares 3 entries but keyword 'End'",
              line=14)


def test_wrong_counts_tetgen(tmp_path: Path) -> None:
    node, ele = tetgen_texts(X2, T2)
    p = write_tetgen(tmp_path, node.replace("5 3 0 0", "4 3 0 0", 1), ele)
    raises_at(read_tet_mesh, p.with_suffix(".node"), r"more data than the header's 4 points",
              line=6)
    p = write_tetgen(tmp_path, node, ele.replace("2 4 0", "3 4 0", 1), stem="e")
    raises_at(read_tet_mesh, p, r"truncated.*declares 3 entries", line=3)


# ------------------------------------------------------------------------ non-numeric / non-finite


def test_non_numeric_tokens(tmp_path: Path) -> None:
    lines = medit_lines()
    lines[6] = "0.0 abc 0.0 0"  # vertex 2 (0-based)
    p = write(tmp_path / "abc.mesh", "\n".join(lines))
    raises_at(read_tet_mesh, p, r"non-numeric token 'abc' in Vertices", line=7, element=2)
    lines = medit_lines()
    lines[12] = "2 5 x 4 0"
    p = write(tmp_path / "abct.mesh", "\n".join(lines))
    raises_at(read_tet_mesh, p, r"non-numeric token 'x' in Tetrahedra .*integer", line=13,
              element=1)
    node, ele = tetgen_texts(X2, T2)
    node_lines = node.split("\n")
    node_lines[3] = "2 0.0 1,0 0.0"
    p = write_tetgen(tmp_path, "\n".join(node_lines), ele)
    raises_at(read_tet_mesh, p.with_suffix(".node"), r"non-numeric token '1,0'", line=4,
              element=2)
    text = obj_text(X2, F2).replace("f 1 3 2", "f 1 three 2")
    p = write(tmp_path / "abc.obj", text)
    raises_at(read_surface_mesh, p, r"bad vertex index 'three'", line=6, element=0)
    text = obj_text(X2, F2).replace("v 1.0 0.0 0.0", "v 1.0 O.0 0.0")
    p = write(tmp_path / "abcv.obj", text)
    raises_at(read_surface_mesh, p, r"non-numeric coordinate 'O.0'", line=2, element=1)


def test_coordinates_too_large_or_small(tmp_path: Path) -> None:
    for scale in (1e90, 1e-90):
        p = write(tmp_path / "scale.mesh", medit_text(X2 * scale, T2))
        raises_at(read_tet_mesh, p, r"double precision cannot work with", line=12, element=0)
    # finite, but the sliver it makes is degenerate
    X = X2.copy()
    X[4] = [1e200, 1.0, 1.0]
    p = write(tmp_path / "far.mesh", medit_text(X, T2))
    raises_at(read_tet_mesh, p, r"degenerate", line=13, element=1)


def test_latin1_and_bom_are_tolerated(tmp_path: Path) -> None:
    p = tmp_path / "latin.obj"
    p.write_bytes(b"# cr\xe9\xe9 par moi\n" + obj_text(X2, F2).encode())
    V, F = read_surface_mesh(p)
    assert F.shape == (4, 3)
    p = tmp_path / "bom.mesh"
    p.write_bytes(b"\xef\xbb\xbf" + medit_text(X2, T2).encode())
    assert read_tet_mesh(p).n_tets == 2


def test_binary_garbage(tmp_path: Path) -> None:
    p = tmp_path / "bin.mesh"
    p.write_bytes(b"MeshVersionFormatted 1\n\xff\xfe\x00garbage")
    raises_at(read_tet_mesh, p, r"not a text file", line=2)
    p = tmp_path / "bin.vtu"
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    raises_at(read_tet_mesh, p, r"not a readable VTU file")


@pytest.mark.parametrize("bad", ["nan", "inf", "-Infinity", "1e999"])
def test_non_finite_coordinates(tmp_path: Path, bad: str) -> None:
    lines = medit_lines()
    lines[7] = f"0.0 1.0 {bad} 0"  # vertex 3 (0-based), 4 in the file
    p = write(tmp_path / "nan.mesh", "\n".join(lines))
    raises_at(read_tet_mesh, p, r"vertex 4 has a non-finite coordinate", line=8, element=3)
    node, ele = tetgen_texts(X2, T2)
    node_lines = node.split("\n")
    node_lines[5] = f"4 {bad} 1.0 1.0"
    p = write_tetgen(tmp_path, "\n".join(node_lines), ele)
    raises_at(read_tet_mesh, p.with_suffix(".node"), r"vertex 4 has a non-finite", line=6,
              element=4)
    text = obj_text(X2, F2).replace("v 0.0 0.0 1.0", f"v 0.0 0.0 {bad}")
    p = write(tmp_path / "nan.obj", text)
    raises_at(read_surface_mesh, p, r"vertex 4 has a non-finite", line=4, element=3)


# ------------------------------------------------------------------------ indices


@pytest.mark.parametrize(("bad", "hint"), [("6", "valid indices are 1..5"),
                                           ("0", "1-based"), ("-3", "valid indices")])
def test_index_out_of_range_medit(tmp_path: Path, bad: str, hint: str) -> None:
    lines = medit_lines()
    lines[12] = f"2 {bad} 3 4 0"
    p = write(tmp_path / "idx.mesh", "\n".join(lines))
    raises_at(read_tet_mesh, p, rf"index out of range: tet 1 .*{hint}", line=13, element=1)


@pytest.mark.parametrize("bad", ["5", "-1", "2.5", "nan"])
def test_index_out_of_range_tetgen(tmp_path: Path, bad: str) -> None:
    node, ele = tetgen_texts(X2, T2)
    ele_lines = ele.split("\n")
    ele_lines[1] = f"0 0 1 {bad} 3"
    p = write_tetgen(tmp_path, node, "\n".join(ele_lines))
    raises_at(read_tet_mesh, p, r"out of range|non-integer", line=2, element=0)


@pytest.mark.parametrize(("face", "elem"), [("f 1 2 6", 2), ("f 1 -7 2", 2), ("f 0 1 2", 2)])
def test_index_out_of_range_obj(tmp_path: Path, face: str, elem: int) -> None:
    text = obj_text(X2, F2).replace("f 1 4 3", face)
    p = write(tmp_path / "idx.obj", text)
    raises_at(read_surface_mesh, p, r"out of range|index 0", line=8, element=elem)


def test_first_tetgen_index_must_be_0_or_1(tmp_path: Path) -> None:
    node, ele = tetgen_texts(X2, T2, base=2)
    p = write_tetgen(tmp_path, node, ele)
    raises_at(read_tet_mesh, p.with_suffix(".node"), r"first node index must be 0 or 1", line=2,
              element=0)
    node, ele = tetgen_texts(X2, T2)
    p = write_tetgen(tmp_path, node.replace("\n3 ", "\n7 "), ele, stem="gap")
    raises_at(read_tet_mesh, p.with_suffix(".node"), r"consecutive: expected 3, found 7", line=5,
              element=3)


# ------------------------------------------------------------------------ bad tets


def test_repeated_vertices(tmp_path: Path) -> None:
    lines = medit_lines()
    lines[12] = "2 5 3 5 0"
    p = write(tmp_path / "rep.mesh", "\n".join(lines))
    raises_at(read_tet_mesh, p, r"tet 1 has a repeated vertex \[2, 5, 3, 5\]", line=13,
              element=1)
    node, ele = tetgen_texts(X2, T2)
    p = write_tetgen(tmp_path, node, ele.replace("\n0 0 1 2 3", "\n0 0 1 1 3"))
    raises_at(read_tet_mesh, p, r"repeated vertex", line=2, element=0)


def test_duplicate_and_overlapping_tets(tmp_path: Path) -> None:
    p = write(tmp_path / "dup.mesh", medit_text(X2, np.vstack([T2, T2[:1][:, [1, 0, 2, 3]]])))
    raises_at(read_tet_mesh, p, r"tet 2 duplicates tet 0", line=14, element=2)
    X = np.vstack([X2, [[0.2, 0.2, -1.0], [0.2, 0.2, 0.5]]])
    T = np.vstack([T2, [[0, 2, 1, 5], [0, 1, 2, 6]]])  # three tets on face (0, 1, 2)
    p = write(tmp_path / "over.mesh", medit_text(X, T))
    raises_at(read_tet_mesh, p, r"tet 3 has face \[1, 3, 2\] that tets 0, 2 already share",
              line=17, element=3)


def test_zero_volume_tets(tmp_path: Path) -> None:
    X = X2.copy()
    X[4] = [0.5, 0.5, 0.0]  # in the plane of vertices 1, 2 and (0): tet 1 = (1, 4, 2, 3) ok
    T = np.array([[0, 1, 2, 3], [0, 1, 4, 2]])  # tet 1 is flat (all z = 0)
    p = write(tmp_path / "flat.mesh", medit_text(X, T))
    raises_at(read_tet_mesh, p, r"tet 1 \(vertices \[1, 2, 5, 3\]\) is degenerate", line=13,
              element=1)
    # relative tolerance: a sliver of relative height 1e-10 is degenerate at any scale ...
    X[4] = [0.5, 0.5, 1e-10]
    for scale in (1e-6, 1.0, 1e6):
        p = write(tmp_path / "sliver.mesh", medit_text(X * scale, T))
        raises_at(read_tet_mesh, p, r"degenerate", line=13, element=1)
    # ... and a tiny but well-shaped mesh is fine
    p = write(tmp_path / "tiny.mesh", medit_text(X2 * 1e-9, T2))
    assert_valid_tet_mesh(read_tet_mesh(p))
    # coincident vertices (different indices, same position)
    X = X2.copy()
    X[4] = X[1]
    p = write(tmp_path / "coinc.mesh", medit_text(X, T2))
    raises_at(read_tet_mesh, p, r"degenerate", line=13, element=1)


def test_no_tets(tmp_path: Path) -> None:
    text = medit_text(X2, T2)
    no_section = text[: text.index("Tetrahedra")] + "End\n"
    raises_at(read_tet_mesh, write(tmp_path / "none.mesh", no_section), r"no tetrahedra")
    zero = text[: text.index("Tetrahedra")] + "Tetrahedra\n0\nEnd\n"
    raises_at(read_tet_mesh, write(tmp_path / "zero.mesh", zero), r"no tetrahedra")
    node, _ = tetgen_texts(X2, T2)
    p = write_tetgen(tmp_path, node, "0 4 0\n")
    raises_at(read_tet_mesh, p, r"no tetrahedra", line=1)
    write_surface_mesh(tmp_path / "tri.vtu", X2[:4], F2)
    raises_at(read_tet_mesh, tmp_path / "tri.vtu", r"no tetrahedra")


def test_display_mesh_without_vertices(tmp_path: Path) -> None:
    p = write(tmp_path / "nov.obj", "# only faces\nf 1 2 3\n")
    raises_at(read_surface_mesh, p, r"display mesh has no vertices")
    p = write(tmp_path / "nof.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    raises_at(read_surface_mesh, p, r"display mesh has no faces")
    p = write(tmp_path / "empty.mesh", "MeshVersionFormatted 1\nDimension 3\nVertices\n0\nEnd\n")
    raises_at(read_surface_mesh, p, r"display mesh has no vertices")


def test_other_medit_problems(tmp_path: Path) -> None:
    p = write(tmp_path / "dim2.mesh", medit_text(X2, T2).replace("Dimension 3", "Dimension 2"))
    raises_at(read_tet_mesh, p, r"only 3-D", line=2)
    p = write(tmp_path / "kw.mesh", medit_text(X2, T2).replace("Tetrahedra", "Tetrahedrons"))
    raises_at(read_tet_mesh, p, r"unknown MEDIT keyword 'Tetrahedrons'", line=10)
    p = write(tmp_path / "neg.mesh", medit_text(X2, T2).replace("Tetrahedra\n2", "Tetrahedra\n-2"))
    raises_at(read_tet_mesh, p, r"must be >= 0", line=11)


# ------------------------------------------------------------------------ property tests

SEED_TEXTS: dict[str, bytes] = {}


def _seeds() -> dict[str, bytes]:
    """Small shipped (or derived) files to corrupt, keyed by file name."""
    if not SEED_TEXTS:
        arma = read_tet_mesh(DATA / "arma_6")
        SEED_TEXTS["coarser_bunny.mesh"] = (DATA / "coarser_bunny.mesh").read_bytes()
        SEED_TEXTS["arma_6.node"] = (DATA / "arma_6.node").read_bytes()
        SEED_TEXTS["arma_6.ele"] = (DATA / "arma_6.ele").read_bytes()
        SEED_TEXTS["armadillo2.obj"] = (DATA / "armadillo2.obj").read_bytes()
        SEED_TEXTS["coarser_bunny.obj"] = (DATA / "coarser_bunny.obj").read_bytes()
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            write_tet_mesh(Path(d) / "arma.msh", arma)  # gmsh 2.2 ASCII
            write_tet_mesh(Path(d) / "small.vtu", arma)
            SEED_TEXTS["arma.msh"] = (Path(d) / "arma.msh").read_bytes()
            SEED_TEXTS["arma.vtu"] = (Path(d) / "small.vtu").read_bytes()
    return SEED_TEXTS


READERS: dict[str, Callable] = {
    ".mesh": read_tet_mesh,
    ".node": read_tet_mesh,
    ".ele": read_tet_mesh,
    ".msh": read_tet_mesh,
    ".vtu": read_tet_mesh,
    ".obj": read_surface_mesh,
}


def _check_reader(path: Path, reader: Callable) -> str:
    """Run a reader: InputError or a fully valid mesh. Returns the outcome."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # any warning but a MeshWarning is a bug
            warnings.simplefilter("ignore", MeshWarning)
            out = reader(path)
    except InputError as err:
        assert path.name in str(err) or path.stem in str(err), str(err)
        return "error"
    if isinstance(out, TetMesh):
        assert_valid_tet_mesh(out)
    else:
        assert_valid_surface(*out)
    return "ok"


TOKENS = [b"nan", b"-1", b"abc", b"0", b"inf", b"1e308", b"99999999999999999999", b"", b"1.5"]

# a corruption: (operation, position as a fraction of the file, argument)
OPS = st.tuples(
    st.sampled_from(["flip", "truncate", "delete_line", "token"]),
    st.floats(0.0, 1.0, exclude_max=True),
    st.integers(0, 254),
)


_SEED_SPANS: dict[bytes, list[tuple[int, int]]] = {}


def _token_spans(data: bytes) -> list[tuple[int, int]]:
    """The (start, end) of every whitespace-separated token; memoised for the seed files,
    which most examples corrupt first (scanning a 50 kB seed took a third of the test)."""
    if data in _SEED_SPANS:
        return _SEED_SPANS[data]
    spans = [m.span() for m in re.finditer(rb"\S+", data)]
    if data in SEED_TEXTS.values():
        _SEED_SPANS[data] = spans
    return spans


def _write_fresh(path: Path, data: bytes) -> None:
    """Write ``data`` to a new inode: truncating an existing file on ext4 flushes it to disk
    on close (auto_da_alloc, ~2 ms a file), which dominated thousands of examples."""
    path.unlink(missing_ok=True)
    path.write_bytes(data)


def corrupt(data: bytes, ops: list[tuple[str, float, int]]) -> bytes:
    """Apply byte flips, truncation, line deletion and token replacement."""
    for op, where, arg in ops:
        if not data:
            break
        if op == "flip":
            i = int(where * len(data))
            data = data[:i] + bytes([data[i] ^ (arg + 1)]) + data[i + 1:]
        elif op == "truncate":
            data = data[: int(where * len(data))]
        elif op == "delete_line":
            lines = data.split(b"\n")
            i = int(where * len(lines))
            data = b"\n".join(lines[:i] + lines[i + 1:])
        else:
            spans = _token_spans(data)
            if spans:
                a, b = spans[int(where * len(spans))]
                data = data[:a] + TOKENS[arg % len(TOKENS)] + data[b:]
    return data


OUTCOMES: dict[str, int] = {}


@settings(max_examples=1000, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(name=st.sampled_from(["coarser_bunny.mesh", "arma_6.node", "arma_6.ele",
                             "armadillo2.obj", "coarser_bunny.obj", "arma.msh", "arma.vtu"]),
       ops=st.lists(OPS, min_size=1, max_size=3))
def test_corrupted_shipped_meshes(tmp_path: Path, name: str,
                                  ops: list[tuple[str, float, int]]) -> None:
    seeds = _seeds()
    path = tmp_path / ("c_" + name)
    _write_fresh(path, corrupt(seeds[name], ops))
    if path.suffix in (".node", ".ele"):  # the TetGen partner file, uncorrupted
        partner = Path(name).with_suffix(".ele" if path.suffix == ".node" else ".node").name
        _write_fresh(tmp_path / ("c_" + partner), seeds[partner])
    outcome = _check_reader(path, READERS[path.suffix])
    OUTCOMES[outcome] = OUTCOMES.get(outcome, 0) + 1


@settings(max_examples=600, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=512), suffix=st.sampled_from(sorted(READERS)))
def test_random_bytes(tmp_path: Path, data: bytes, suffix: str) -> None:
    path = tmp_path / f"r{suffix}"
    _write_fresh(path, data)
    if suffix in (".node", ".ele"):
        _write_fresh(tmp_path / "r.node", data)
        _write_fresh(tmp_path / "r.ele", data)
    _check_reader(path, READERS[suffix])


@settings(max_examples=600, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(alphabet=st.sampled_from(list("0123456789 .-e\nnaifvVTtrx/#")), max_size=300),
       head=st.sampled_from(["MeshVersionFormatted 1\nDimension 3\nVertices\n", "4 3 0 0\n",
                             "v 0 0 0\nv 1 0 0\nv 0 1 0\n", ""]),
       suffix=st.sampled_from([".mesh", ".node", ".obj"]))
def test_random_text(tmp_path: Path, text: str, head: str, suffix: str) -> None:
    path = tmp_path / f"t{suffix}"
    _write_fresh(path, (head + text).encode())
    if suffix == ".node":
        _write_fresh(tmp_path / "t.ele", b"1 4 0\n0 0 1 2 3\n")
    _check_reader(path, READERS[suffix])

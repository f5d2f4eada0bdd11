"""Helpers shared by tests/mesh/test_formats.py and tests/mesh/test_bad_mesh_files.py (not a
conftest)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "data"

# two positively oriented tets sharing the face (1, 2, 3)
X2 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
T2 = np.array([[0, 1, 2, 3], [1, 4, 2, 3]])


def medit_text(X: np.ndarray, T: np.ndarray, *, base: int = 1, version: int = 1) -> str:
    """A MEDIT .mesh file as text (one record per line)."""
    lines = [f"MeshVersionFormatted {version}", "Dimension 3", "Vertices", str(len(X))]
    lines += [f"{x!r} {y!r} {z!r} 0" for x, y, z in np.asarray(X, float).tolist()]
    lines += ["Tetrahedra", str(len(T))]
    lines += [" ".join(str(int(i) + base) for i in t) + " 0" for t in np.asarray(T)]
    lines += ["End", ""]
    return "\n".join(lines)


def tetgen_texts(X: np.ndarray, T: np.ndarray, *, base: int = 0) -> tuple[str, str]:
    """TetGen .node and .ele contents."""
    node = [f"{len(X)} 3 0 0"] + [
        f"{i + base} {x!r} {y!r} {z!r}" for i, (x, y, z) in enumerate(np.asarray(X, float).tolist())
    ]
    ele = [f"{len(T)} 4 0"] + [
        f"{j + base} " + " ".join(str(int(i) + base) for i in t) for j, t in enumerate(T)
    ]
    return "\n".join(node) + "\n", "\n".join(ele) + "\n"


def obj_text(V: np.ndarray, F: np.ndarray) -> str:
    """An OBJ file with ``v`` and ``f a b c`` lines."""
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(V, float).tolist()]
    lines += ["f " + " ".join(str(int(i) + 1) for i in f) for f in F]
    return "\n".join(lines) + "\n"


def assert_valid_tet_mesh(mesh) -> None:
    """Everything fem3d promises about a TetMesh."""
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    assert X.dtype == np.float64 and X.ndim == 2 and X.shape[1] == 3 and X.shape[0] > 0
    assert T.dtype == np.int64 and T.ndim == 2 and T.shape[1] == 4 and T.shape[0] > 0
    assert np.isfinite(X).all()
    assert T.min() >= 0 and T.max() < X.shape[0]
    e = X[T]
    det = np.linalg.det(np.stack([e[:, 1] - e[:, 0], e[:, 2] - e[:, 0], e[:, 3] - e[:, 0]], -1))
    assert (det > 0).all()
    assert (np.diff(np.sort(T, axis=1), axis=1) > 0).all()


def assert_valid_surface(V: np.ndarray, F: np.ndarray) -> None:
    """Everything fem3d promises about a display mesh."""
    assert V.dtype == np.float64 and V.ndim == 2 and V.shape[1] == 3 and V.shape[0] > 0
    assert F.dtype == np.int64 and F.ndim == 2 and F.shape[1] == 3 and F.shape[0] > 0
    assert np.isfinite(V).all()
    assert F.min() >= 0 and F.max() < V.shape[0]

"""Closed surface -> tet mesh with fTetWild (the ``wildmeshing`` bindings), cached.

A scene body whose ``mesh`` is a surface (OBJ/STL/PLY/OFF) is tetrahedralized here:

* fTetWild (Hu et al., "Fast Tetrahedral Meshing in the Wild", 2020) through the PyPI package
  ``wildmeshing`` (numpy in, numpy out; its only other dependency is ``svgwrite``). The
  alternative binding ``pytetwild`` wraps the same library but imports PyVista/VTK (hundreds
  of MB) at ``import pytetwild``; nothing here needs VTK.
* Options: ``edge_length`` (target edge length relative to the bounding-box diagonal: the size
  knob) and ``epsilon`` (envelope: how far the tet boundary may deviate from the surface,
  relative to the diagonal: the fidelity knob), ``stop_quality`` (fTetWild's max-AMIPS energy
  it optimises down to: the quality knob; larger is faster and worse).
* It runs in a child process (``python -m fem3d.mesh.tetrahedralize``): fTetWild prints its log
  straight to the C++ streams, can take long and can crash on pathological input. The log
  goes to ``<cache>/tetwild/<key>.log``, a time limit applies (``$FEM3D_TETWILD_TIMEOUT``
  seconds, default 900), and a crash is an :class:`~fem3d.errors.InputError`.
* The result is cached in ``<cache>/tetwild/<key>.mesh`` (MEDIT), ``<key>`` the sha256 of the
  input file's bytes, the options and the wildmeshing version; ``<cache>`` is the folder the
  caller passes, by default :func:`fem3d.io.files.cache_dir` (``$FEM3D_CACHE`` or
  ``~/.cache/fem3d``). The second run reads the cached mesh.
* A surface that is not closed is first checked for boundary edges; fTetWild's winding-number
  filter repairs small holes. When what comes back has no tets, or a volume far from the
  surface's enclosed volume (an open sheet, not a solid), the surface is refused with one line
  naming the file.
* Threads: ``$FEM3D_TETWILD_THREADS`` (default 0: all cores).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np

from fem3d.errors import InputError
from fem3d.io.extras import MissingExtra, has_module, install_hint
from fem3d.io.files import atomic_write, cache_dir
from fem3d.mesh.formats import read_surface_mesh, read_tet_mesh, write_tet_mesh
from fem3d.mesh.tetmesh import TetMesh

__all__ = ["tetrahedralize_file", "tetrahedralize_arrays", "cache_key", "boundary_edge_count",
           "enclosed_volume", "TETWILD_VERSION"]


def _wildmeshing_version() -> str:
    try:
        return version("wildmeshing")
    except Exception:  # pragma: no cover - not installed
        return "missing"


#: Version of the fTetWild binding (part of the cache key).
TETWILD_VERSION = _wildmeshing_version()


def boundary_edge_count(F: np.ndarray) -> int:
    """Edges used by one triangle only (0 for a closed, manifold-edged surface)."""
    F = np.asarray(F, dtype=np.int64)
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts == 1).sum())


def enclosed_volume(V: np.ndarray, F: np.ndarray) -> float:
    """Signed volume enclosed by a triangle surface (divergence theorem; |.| if inconsistent)."""
    a, b, c = (np.asarray(V, dtype=np.float64)[np.asarray(F)[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def cache_key(path: str | os.PathLike[str], edge_length: float, epsilon: float,
              stop_quality: float) -> str:
    """sha256 of the file's bytes, the options and the binding's version."""
    h = hashlib.sha256(Path(path).read_bytes())
    h.update(json.dumps({"edge_length": float(edge_length), "epsilon": float(epsilon),
                         "stop_quality": float(stop_quality), "tetwild": TETWILD_VERSION},
                        sort_keys=True).encode())
    return h.hexdigest()


def tetrahedralize_arrays(V: np.ndarray, F: np.ndarray, *, edge_length: float = 0.05,
                          epsilon: float = 1e-3, stop_quality: float = 10.0,
                          threads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """fTetWild in this process (prints its log on the C++ streams).

    Returns
    -------
    X : (n, 3) float64
    T : (m, 4) int64
        Interior tets only (winding-number filter); possibly empty.
    """
    import wildmeshing as wm  # optional (fem3d[scenes]); only surface bodies need it

    if threads is None:  # 0: all cores
        threads = int(os.environ.get("FEM3D_TETWILD_THREADS", "0") or 0)

    tw = wm.Tetrahedralizer(stop_quality=float(stop_quality), epsilon=float(epsilon),
                            edge_length_r=float(edge_length), max_threads=int(threads))
    tw.set_log_level(6)
    tw.set_mesh(np.ascontiguousarray(V, dtype=np.float64),
                np.ascontiguousarray(F, dtype=np.int32))
    tw.tetrahedralize()
    out = tw.get_tet_mesh(correct_surface_orientation=True)
    X = np.asarray(out[0], dtype=np.float64).reshape(-1, 3)
    T = np.asarray(out[1], dtype=np.int64).reshape(-1, 4)
    return X, T


def _timeout() -> float:
    try:
        return float(os.environ.get("FEM3D_TETWILD_TIMEOUT", "900"))
    except ValueError:
        return 900.0


def tetrahedralize_file(
    path: str | os.PathLike[str], *, edge_length: float = 0.05, epsilon: float = 1e-3,
    stop_quality: float = 10.0, cache: str | os.PathLike[str] | None = None,
) -> tuple[np.ndarray, np.ndarray, str]:
    """The tet mesh of a closed surface file, from the cache or made by fTetWild.

    Parameters
    ----------
    path : path
        OBJ/STL/PLY/OFF surface (:func:`fem3d.mesh.formats.read_surface_mesh`).
    edge_length, epsilon : float
        Relative to the bounding-box diagonal (see the module docstring).
    stop_quality : float
        fTetWild's target max-AMIPS energy.
    cache : path, optional
        The cache folder; the meshes go to ``<cache>/tetwild/``. Default:
        :func:`fem3d.io.files.cache_dir`.

    Returns
    -------
    X : (n, 3) float64
    T : (m, 4) int64
        Positively oriented (read back through :func:`fem3d.mesh.formats.read_tet_mesh`).
    mesh_path : str
        The cached ``.mesh``.

    Raises
    ------
    InputError
        Unreadable surface, no binding, fTetWild failed or timed out, or a surface it could
        not turn into a solid (naming ``path``).
    """
    path = Path(path)
    V, F = read_surface_mesh(path)
    key = cache_key(path, edge_length, epsilon, stop_quality)
    folder = (cache_dir() if cache is None else Path(cache)) / "tetwild"
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / f"{key[:40]}.mesh"
    if not out.is_file():
        if TETWILD_VERSION == "missing" or not has_module("wildmeshing"):
            raise MissingExtra("is a surface; tetrahedralizing it needs fTetWild (module "
                               f"wildmeshing): {install_hint('wildmeshing')}", path=path)
        log = folder / f"{key[:40]}.log"
        tmp = folder / f".{key[:40]}.{os.getpid()}.npz"
        cmd = [sys.executable, "-m", "fem3d.mesh.tetrahedralize", str(path.resolve()), str(tmp),
               repr(float(edge_length)), repr(float(epsilon)), repr(float(stop_quality))]
        t0 = time.perf_counter()
        work = Path(tempfile.mkdtemp(dir=folder, prefix=".work"))  # fTetWild writes into cwd
        try:
            with open(log, "wb") as fh:
                proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=work,
                                      timeout=_timeout(), env=_child_env())
        except subprocess.TimeoutExpired:
            tmp.unlink(missing_ok=True)
            raise InputError(f"fTetWild took over {_timeout():g} s (FEM3D_TETWILD_TIMEOUT); "
                             f"try a larger tetrahedralize.edge_length", path=path) from None
        finally:
            shutil.rmtree(work, ignore_errors=True)
        seconds = time.perf_counter() - t0
        if proc.returncode != 0 or not tmp.is_file():
            tmp.unlink(missing_ok=True)
            raise InputError(f"fTetWild failed (exit status {proc.returncode}; log {log})",
                             path=path)
        with np.load(tmp) as d:
            X, T = d["X"], d["T"]
        tmp.unlink(missing_ok=True)
        _check_solid(path, V, F, X, T)
        atomic_write(out, lambda p: write_tet_mesh(p, TetMesh(X, T)))
        meta = {"source": str(path.resolve()), "edge_length": edge_length, "epsilon": epsilon,
                "stop_quality": stop_quality, "tetwild": TETWILD_VERSION,
                "seconds": round(seconds, 3), "vertices": int(X.shape[0]),
                "tets": int(T.shape[0])}
        atomic_write(folder / f"{key[:40]}.json", json.dumps(meta, indent=1) + "\n")
    mesh = read_tet_mesh(out)
    return mesh.X, mesh.T, str(out)


def _child_env() -> dict[str, str]:
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])  # the folder holding the fem3d package
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _check_solid(path: Path, V: np.ndarray, F: np.ndarray, X: np.ndarray, T: np.ndarray) -> None:
    holes = boundary_edge_count(F)
    if T.shape[0] == 0:
        what = f"it has {holes} boundary edges (not closed)" if holes else "no interior found"
        raise InputError(f"fTetWild made no tets from this surface: {what}", path=path)
    a, b, c, d = (X[T[:, i]] for i in range(4))
    vol = float(np.abs(np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))).sum() / 6.0)
    enclosed = abs(enclosed_volume(V, F))
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    if holes and not (0.5 * enclosed <= vol <= 2.0 * enclosed):
        raise InputError(
            f"not a closed surface ({holes} boundary edges) and fTetWild could not repair it: "
            f"tet volume {vol:.4g} vs enclosed volume {enclosed:.4g}", path=path)
    if vol < 1e-9 * diag ** 3:
        raise InputError("fTetWild made only degenerate tets (a flat or empty surface)",
                         path=path)


def _main(argv: list[str]) -> int:
    """Child process: ``python -m fem3d.mesh.tetrahedralize IN OUT.npz EDGE EPS QUALITY``."""
    src, dst, edge, eps, quality = argv
    V, F = read_surface_mesh(src)
    X, T = tetrahedralize_arrays(V, F, edge_length=float(edge), epsilon=float(eps),
                                 stop_quality=float(quality))
    np.savez(dst, X=X, T=T)
    return 0


if __name__ == "__main__":  # pragma: no cover - exercised through tetrahedralize_file
    sys.exit(_main(sys.argv[1:]))

"""Reproducible surface bodies: the tet mesh a run used, kept; ``fem3d tetrahedralize``.

fTetWild's output differs from run to run and machine to machine (threads, CPU), so a scene
whose body is a closed surface may run on other tets elsewhere. Two ways to pin it down:

* every run of such a scene writes the tet mesh each surface body ran on into its folder,
  ``meshes/body<i>.mesh`` (the same bytes the run read), with ``meshes/meshes.json``: the
  surface, its options, the SHA-256 of the surface and of the tet mesh, the counts;
* ``fem3d tetrahedralize SURFACE --out FILE.mesh`` writes a surface's tet mesh (the cached one
  when there is one) so that a scene's ``mesh =`` can name it.

A scene whose ``mesh`` names either file runs on exactly those tets on any machine.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from fem3d.errors import InputError
from fem3d.io.files import atomic_write, check_input_file
from fem3d.mesh.formats import read_tet_mesh
from fem3d.mesh.tetrahedralize import TETWILD_VERSION, tetrahedralize_file
from fem3d.scene.arrays import is_surface_file
from fem3d.scene.spec import SURFACE_SUFFIXES, TetrahedralizeSpec, describe_error

__all__ = ["record_tet_meshes", "write_tet_mesh_of", "add_tetrahedralize_subcommand",
           "MESHES_DIR", "MESHES_JSON"]

#: Folder of a run's surface bodies' tet meshes, and their record.
MESHES_DIR = "meshes"
MESHES_JSON = "meshes.json"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def record_tet_meshes(scene, mesh_paths: list[str], out: Path) -> list[dict[str, Any]]:
    """Write the tet mesh of every surface body of ``scene`` into ``out/meshes/``.

    Parameters
    ----------
    scene : fem3d.scene.spec.Scene
    mesh_paths : list of str
        The tet mesh each body was read from (``Simulation.assembled.mesh_paths``; a surface
        body's is fTetWild's cached ``.mesh``).
    out : Path
        The run folder.

    Returns
    -------
    list of dict
        One record per surface body (what ``meshes/meshes.json`` holds); empty when no body is
        a surface (then nothing is written).
    """
    records = []
    for i, body in enumerate(scene.bodies):
        surface = scene.path(body.mesh)
        if not is_surface_file(surface):
            continue
        data = Path(mesh_paths[i]).read_bytes()
        name = f"body{i}.mesh"
        (out / MESHES_DIR).mkdir(parents=True, exist_ok=True)
        atomic_write(out / MESHES_DIR / name, data)
        mesh = read_tet_mesh(out / MESHES_DIR / name)
        records.append({
            "body": i, "name": body.label, "mesh": f"{MESHES_DIR}/{name}", "sha256": _sha256(data),
            "vertices": int(mesh.X.shape[0]), "tets": int(mesh.T.shape[0]),
            "surface": str(surface), "surface_sha256": _sha256(surface.read_bytes()),
            "tetrahedralize": body.tetrahedralize.model_dump(), "tetwild": TETWILD_VERSION,
        })
    if records:
        text = json.dumps({"bodies": records}, indent=1) + "\n"
        atomic_write(out / MESHES_DIR / MESHES_JSON, text)
    return records


def write_tet_mesh_of(surface: str | Path, out: str | Path | None = None,
                      options: dict[str, float] | None = None) -> tuple[Path, dict[str, Any]]:
    """Tetrahedralize ``surface`` (or take the cached mesh) and write it to ``out``.

    Parameters
    ----------
    surface : path
        A closed OBJ/STL/PLY/OFF surface.
    out : path, optional
        The ``.mesh`` (MEDIT) to write; default ``<surface stem>.mesh`` in the current folder.
    options : dict, optional
        ``edge_length``, ``epsilon``, ``stop_quality`` (a scene body's ``tetrahedralize``).

    Returns
    -------
    path : Path
    info : dict
        ``vertices``, ``tets``, ``sha256`` of the written file.

    Raises
    ------
    InputError
        Not a surface file, a bad option, ``out`` not a ``.mesh`` or the surface itself, or
        fTetWild's own refusal.
    """
    src = check_input_file(surface, "surface")
    if not is_surface_file(src):
        raise InputError(f"not a surface file (expected {', '.join(SURFACE_SUFFIXES)})",
                         path=src)
    try:
        opts = TetrahedralizeSpec.model_validate(
            {k: float(v) for k, v in (options or {}).items() if v is not None})
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        raise InputError(f"--{str(err['loc'][0]).replace('_', '-')}: "
                         f"{describe_error(err)}") from None
    dst = Path(out) if out is not None else Path(f"{src.stem}.mesh")
    if dst.suffix.lower() != ".mesh":
        raise InputError("--out must name a .mesh file (MEDIT)", path=dst)
    if dst.exists() and dst.resolve() == src.resolve():
        raise InputError("--out is the input surface", path=dst)
    _, _, cached = tetrahedralize_file(src, **opts.model_dump())
    data = Path(cached).read_bytes()
    if dst.parent != Path(""):
        dst.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(dst, data)
    mesh = read_tet_mesh(dst)
    return dst, {"vertices": int(mesh.X.shape[0]), "tets": int(mesh.T.shape[0]),
                 "sha256": _sha256(data)}


def _tetrahedralize_command(args: argparse.Namespace) -> int:
    opts = {"edge_length": args.edge_length, "epsilon": args.epsilon,
            "stop_quality": args.stop_quality}
    dst, info = write_tet_mesh_of(args.surface, args.out, opts)
    print(f"{dst}: {info['vertices']} vertices, {info['tets']} tets, sha256 "
          f"{info['sha256'][:16]}... (a scene body's mesh = \"{dst}\" runs on these tets)")
    return 0


def add_tetrahedralize_subcommand(subparsers) -> argparse.ArgumentParser:
    """Register ``fem3d tetrahedralize``."""
    dflt = TetrahedralizeSpec()
    p = subparsers.add_parser(
        "tetrahedralize", help="write a closed surface's tet mesh (fTetWild) to a .mesh file",
        description="Tetrahedralize a closed surface with fTetWild (or take the cached result) "
        "and write the tet mesh, so that a scene's mesh = can name it and run on the same tets "
        "on any machine (fTetWild's output varies from run to run).",
    )
    p.add_argument("surface", help="closed surface: " + ", ".join(SURFACE_SUFFIXES))
    p.add_argument("--out", default=None, help="the .mesh to write (default: SURFACE's stem "
                   ".mesh in the current folder)")
    p.add_argument("--edge-length", type=float, default=dflt.edge_length,
                   help="target edge length relative to the bounding-box diagonal "
                   f"(default {dflt.edge_length})")
    p.add_argument("--epsilon", type=float, default=dflt.epsilon,
                   help=f"envelope relative to the diagonal (default {dflt.epsilon})")
    p.add_argument("--stop-quality", type=float, default=dflt.stop_quality,
                   help=f"fTetWild's target max AMIPS energy (default {dflt.stop_quality})")
    p.set_defaults(func=_tetrahedralize_command)
    return p

"""The frames of a distributed run: each rank writes the surface of its tets as one ``.vtu``
piece, rank 0 the ``.pvtu`` that gathers a frame's pieces and ``frames.pvd`` (ParaView)."""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from fem3d.io.files import atomic_write
from fem3d.io.frames import RawVtu

__all__ = ["PieceWriter"]


class PieceWriter:
    """One rank's frames: the surface of its tets as ``frame_NNNNN_R.vtu``; rank 0 also
    writes each frame's ``.pvtu`` and ``frames.pvd``.

    Parameters
    ----------
    out : Path
    triangles : (t, 3) int64
        The surface of this rank's tets (the whole mesh's vertex numbers): the element's
        ``surface_triangles``.
    comm : mpi4py.MPI.Comm
    display_faces : (f, 3) int64, optional
        Rank 0 of a scene with a display mesh: its triangles (:meth:`write_display`).
    """

    def __init__(self, out: Path, triangles: np.ndarray, comm: Any,
                 display_faces: np.ndarray | None = None) -> None:
        self.rank, self.size = comm.Get_rank(), comm.Get_size()
        self.out = Path(out)
        self.frame_dir = self.out / "frames"
        self.vertices, local = np.unique(triangles, return_inverse=True)
        self._vtu = RawVtu(local.reshape(-1, 3))
        self._display = None if display_faces is None else RawVtu(display_faces)
        self._rank_field = np.full(self.vertices.size, self.rank, dtype=np.int32)
        #: step -> (time, path relative to ``out``) of every frame listed in ``frames.pvd``
        self.frames: dict[int, tuple[float, str]] = {}

    def name(self, step: int, rank: int | None = None) -> str:
        return f"frame_{step:05d}" + ("" if rank is None else f"_{rank}") + \
            (".pvtu" if rank is None else ".vtu")

    def restore(self, frames: Mapping[int, tuple[float, str]], step: int) -> None:
        """Continue a run from a checkpoint at ``step``: its frames (a one-process run's
        ``.vtu`` frames, or pieces) stay listed; rank 0 removes the files of later frames
        (written after the checkpoint) and rewrites ``frames.pvd``."""
        self.frames = {int(k): (float(t), str(r)) for k, (t, r) in frames.items()
                       if int(k) <= step}
        if self.rank:
            return
        for f in self.frame_dir.glob("frame_*.*vtu"):
            with contextlib.suppress(ValueError, IndexError):
                if int(f.stem.split("_")[1]) > step:
                    f.unlink()
        self._write_pvd()

    def write(self, step: int, t: float, q: np.ndarray,
              fields: Mapping[str, np.ndarray] | None = None) -> None:
        """This rank's piece of frame ``step``; rank 0: the ``.pvtu`` and ``frames.pvd``.

        ``fields``: float64 point data over the rank's vertices (``(n,)`` or ``(n, c)``; the
        stress fields of :func:`fem3d.physics.stress.vertex_fields`), the same names on
        every rank; each piece carries them at its points, after its ``rank``."""
        data = {"rank": self._rank_field,
                **{name: np.asarray(a, dtype=np.float64)[self.vertices]
                   for name, a in (fields or {}).items()}}
        self._vtu.write(self.frame_dir / self.name(step, self.rank), q[self.vertices], data)
        if self.rank:
            return
        pieces = "\n".join(f"    <Piece Source={quoteattr(self.name(step, r))}/>"
                           for r in range(self.size))
        arrays = "".join(_p_data_array(name, a) for name, a in data.items())
        atomic_write(self.frame_dir / self.name(step), (
            '<?xml version="1.0"?>\n<VTKFile type="PUnstructuredGrid" version="1.0" '
            'byte_order="LittleEndian" header_type="UInt64">\n'
            '  <PUnstructuredGrid GhostLevel="0">\n'
            f"    <PPointData>{arrays}</PPointData>\n"
            '    <PPoints><PDataArray type="Float64" NumberOfComponents="3"/></PPoints>\n'
            f"{pieces}\n  </PUnstructuredGrid>\n</VTKFile>\n"))
        self.frames[step] = (t, f"frames/{self.name(step)}")
        self._write_pvd()

    def write_display(self, step: int, t: float, V: np.ndarray,
                      fields: Mapping[str, np.ndarray]) -> None:
        """Rank 0: frame ``step`` of the whole display mesh at ``V`` with point ``fields``,
        as one process writes it (``frames/frame_NNNNN.vtu``), and ``frames.pvd``."""
        name = f"frame_{step:05d}.vtu"
        self._display.write(self.frame_dir / name, V, fields)
        self.frames[step] = (t, f"frames/{name}")
        self._write_pvd()

    def _write_pvd(self) -> None:
        rows = "\n".join(f'    <DataSet timestep="{tt!r}" group="" part="0" '
                         f"file={quoteattr(rel)}/>" for _, (tt, rel) in sorted(self.frames.items()))
        atomic_write(self.out / "frames.pvd", (
            '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" '
            f'byte_order="LittleEndian">\n  <Collection>\n{rows}\n  </Collection>\n'
            "</VTKFile>\n"))


def _p_data_array(name: str, a: np.ndarray) -> str:
    """The ``.pvtu``'s declaration of a pieces' point array (its type and components)."""
    kind = "Int32" if a.dtype == np.int32 else "Float64"
    components = int(np.prod(a.shape[1:], dtype=int))
    comps = f' NumberOfComponents="{components}"' if components > 1 else ""
    return f'<PDataArray type="{kind}" Name={quoteattr(name)}{comps}/>'

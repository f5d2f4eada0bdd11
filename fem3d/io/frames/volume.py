"""The volume mesh of a run as VTU frames (``output.volume = true``), beside its frames.

``out_dir/volume/volume_00042.vtu`` per frame (the same steps as the frames, whatever
``output.format``) and the collection ``out_dir/volume.pvd`` (ParaView). A file holds every
node of the simulation mesh at that step and its elements as the element's own VTK cell
(``tetra`` for P1; VTK's quadratic tetrahedron ``tetra10`` for P2, which ParaView draws
curved), with per-element fields as cell data and their vertex averages as point data.
The fields are computed by the caller (:mod:`fem3d.physics.stress`); this module writes
what it is given, encoded like the surface frames (:class:`~fem3d.io.frames.vtu.RawVtu`,
appended raw binary, the cells encoded once).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from fem3d.io.files import PathLike
from fem3d.io.frames.base import check_cells
from fem3d.io.frames.numbered import FileEncoder
from fem3d.io.frames.vtu import RawVtu, VtuWriter

__all__ = ["VOLUME_INDEX", "VolumeVtuWriter"]

#: The collection of the volume frames, in the output folder.
VOLUME_INDEX = "volume.pvd"


class VolumeVtuWriter(VtuWriter):
    """Numbered VTU files of the volume mesh, listed with their times in ``volume.pvd``.

    Parameters
    ----------
    out_dir : str or PathLike
        Output folder (``volume/``, ``volume.pvd``).
    cells : (m, k) int, or a list of them
        The elements' nodes in VTK's order (``k = 4`` tetra, ``k = 10`` tetra10); bodies of
        several elements: one array per element block, written in that order.
    vtk_type : int, or a list of them
        VTK's cell type of the elements (10 ``VTK_TETRA``, 24 ``VTK_QUADRATIC_TETRA``: the
        element's ``vtk_type``), one per block when ``cells`` is a list.
    index_every_frame, digits
        See :class:`~fem3d.io.frames.vtu.VtuWriter`.
    """

    folder = "volume"
    stem = "volume"

    def __init__(self, out_dir: PathLike, cells, vtk_type, *,
                 index_every_frame: bool = True, digits: int = 5) -> None:
        self._blocks = None
        if isinstance(cells, (list, tuple)):  # one block per element
            self._blocks = [(check_cells(c), int(t)) for c, t in zip(cells, vtk_type,
                                                                     strict=True)]
            # every node as a one-node cell: what the base class checks positions against
            cells = np.concatenate([c.reshape(-1) for c, _ in self._blocks])[:, None]
            vtk_type = self._blocks[0][1]
        self.vtk_type = int(vtk_type)
        super().__init__(out_dir, cells, index_every_frame=index_every_frame, digits=digits)
        self.pvd_path = self.out_dir / VOLUME_INDEX

    def check_cells(self, faces: np.ndarray) -> np.ndarray:
        """The elements, checked (any node count per cell)."""
        return check_cells(faces)

    def encoder(self, faces: np.ndarray) -> FileEncoder:
        """:class:`~fem3d.io.frames.vtu.RawVtu` of the element cells."""
        if self._blocks is not None:
            return RawVtu.of_blocks(self._blocks)
        return RawVtu(faces, self.vtk_type)

    def restore(self, frames: Mapping[int, tuple[float, str]], step: int) -> None:
        """Continue a run from a checkpoint's list of the run's frames: the volume files of
        those steps that are on disk are kept, later ones removed, ``volume.pvd`` rewritten."""
        kept = {int(s): (float(t), self.path_of(int(s)).relative_to(self.out_dir).as_posix())
                for s, (t, _) in frames.items()
                if int(s) <= step and self.path_of(int(s)).is_file()}
        super().restore(kept, step)

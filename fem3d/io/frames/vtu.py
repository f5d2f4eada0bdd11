"""VTU frames for ParaView: ``frames/frame_00042.vtu`` and the collection ``frames.pvd``.

- :class:`RawVtu` - VTK XML with appended raw binary data, the triangles encoded once (the
  default encoder).
- :class:`MeshioVtu` - meshio's compressed writer (``compression="zlib"`` or ``"lzma"``).
- :class:`VtuWriter` - the numbered frames and ``frames.pvd`` (the frames and the obstacles'
  files by time, the obstacles as parts 1, 2, ...).
- :data:`FORMAT` - the ``"vtu"`` output format.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

import meshio
import numpy as np

from fem3d.io.files import PathLike, atomic_write
from fem3d.io.frames.base import Bodies, FrameFormat, check_cells, check_faces
from fem3d.io.frames.numbered import FileEncoder, NumberedFilesWriter
from fem3d.io.obstacles import ObstacleMesh

__all__ = ["FORMAT", "MeshioVtu", "RawVtu", "VtuWriter"]

#: VTK's cell type of a triangle.
_VTK_TRIANGLE = 5

#: NumPy dtypes -> VTK XML type names (little endian, as the files say).
_VTK_TYPES = {"<f8": "Float64", "<f4": "Float32", "<i8": "Int64", "<i4": "Int32",
              "|u1": "UInt8", "<u4": "UInt32", "<u8": "UInt64"}


def _le(a: np.ndarray) -> np.ndarray:
    """``a`` contiguous and little endian (the byte order the files declare)."""
    a = np.ascontiguousarray(a)
    return a.astype(a.dtype.newbyteorder("<")) if a.dtype.byteorder == ">" else a


def _data_array(name: str | None, a: np.ndarray, offset: int, components: int) -> str:
    vtk = _VTK_TYPES.get(a.dtype.str)
    if vtk is None:
        raise ValueError(f"field {name!r}: cannot write dtype {a.dtype} to VTU")
    named = f" Name={quoteattr(name)}" if name is not None else ""
    comps = f' NumberOfComponents="{components}"' if components > 1 else ""
    return f'<DataArray type="{vtk}"{named}{comps} format="appended" offset="{offset}"/>'


class RawVtu:
    """VTK XML unstructured grids of one cell mesh, appended raw binary data.

    The cells (connectivity, offsets, cell types) are encoded once; a frame is the XML
    header, the positions' bytes (float64, exactly the values given), the cells' bytes and
    the fields'. No compression, no base64: writing a frame is a few ``memcpy`` and the file
    system's work. ParaView, VTK's ``vtkXMLUnstructuredGridReader`` and meshio read it.

    Parameters
    ----------
    faces : (n_cells, k) int
        Cells (0-based): triangles ``(n_faces, 3)`` by default.
    vtk_type : int
        VTK's cell type of every cell (5 triangle, 10 tetra, 24 quadratic tetra); ``k`` is
        its node count.
    """

    def __init__(self, faces: np.ndarray, vtk_type: int = _VTK_TRIANGLE) -> None:
        F = check_faces(faces) if vtk_type == _VTK_TRIANGLE else check_cells(faces)
        self._encode_cells([(F, int(vtk_type))])

    @classmethod
    def of_blocks(cls, blocks) -> RawVtu:
        """The encoder of cells of several types (bodies of different elements): ``blocks``
        a sequence of ``(cells (m_b, k_b) int, vtk_type)``, written in that order."""
        new = object.__new__(cls)
        new._encode_cells([(check_cells(c), int(t)) for c, t in blocks])
        return new

    def _encode_cells(self, blocks: list[tuple[np.ndarray, int]]) -> None:
        top = max((int(F.max()) for F, _ in blocks if F.size), default=0)
        idx = np.int32 if top < 2**31 - 1 else np.int64
        self.n_cells = sum(int(F.shape[0]) for F, _ in blocks)
        nodes = np.repeat([F.shape[1] for F, _ in blocks], [F.shape[0] for F, _ in blocks])
        self.cells = [  # (name, little-endian array)
            ("connectivity", _le(np.concatenate([F.astype(idx).reshape(-1)
                                                 for F, _ in blocks]))),
            ("offsets", _le(np.cumsum(nodes, dtype=idx))),
            ("types", np.concatenate([np.full(F.shape[0], t, dtype=np.uint8)
                                      for F, t in blocks])),
        ]
        self._cell_bytes = b"".join(
            np.uint64(a.nbytes).tobytes() + a.tobytes() for _, a in self.cells)
        self._headers: dict[tuple, bytes] = {}

    def _header(self, n_points: int, fields: list[tuple[str, np.ndarray, int]],
                cell_fields: list[tuple[str, np.ndarray, int]] = ()) -> bytes:
        key = (n_points, tuple((n, a.dtype.str, c) for n, a, c in fields),
               tuple((n, a.dtype.str, c) for n, a, c in cell_fields))
        if key in self._headers:
            return self._headers[key]
        offset = 0
        points = _data_array(None, np.empty(0, "<f8"), offset, 3)
        offset += 8 + 24 * n_points
        cells = []
        for name, a in self.cells:
            cells.append(_data_array(name, a, offset, 1))
            offset += 8 + a.nbytes
        data, cell_data = [], []
        for name, a, comps in fields:
            data.append(_data_array(name, a, offset, comps))
            offset += 8 + a.nbytes
        for name, a, comps in cell_fields:
            cell_data.append(_data_array(name, a, offset, comps))
            offset += 8 + a.nbytes
        lines = [
            '<?xml version="1.0"?>',
            '<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" '
            'header_type="UInt64">',
            "  <UnstructuredGrid>",
            f'    <Piece NumberOfPoints="{n_points}" NumberOfCells="{self.n_cells}">',
            "      <Points>", f"        {points}", "      </Points>",
            "      <Cells>", *(f"        {c}" for c in cells), "      </Cells>",
        ]
        if data:
            lines += ["      <PointData>", *(f"        {d}" for d in data), "      </PointData>"]
        if cell_data:
            lines += ["      <CellData>", *(f"        {d}" for d in cell_data),
                      "      </CellData>"]
        lines += ["    </Piece>", "  </UnstructuredGrid>", '  <AppendedData encoding="raw">',
                  "   _"]
        header = "\n".join(lines).encode("ascii")
        if len(self._headers) < 8:
            self._headers[key] = header
        return header

    def parts(self, V: np.ndarray, point_data: Mapping[str, np.ndarray] | None = None,
              cell_data: Mapping[str, np.ndarray] | None = None) -> list[bytes]:
        """The file's bytes, in pieces (header, positions, cells, fields, end).

        Parameters
        ----------
        V : (n, 3) float64
            Positions.
        point_data : mapping of str to (n,) or (n, k) arrays, optional
            Extra per-vertex fields.
        cell_data : mapping of str to (n_cells,) or (n_cells, k) arrays, optional
            Per-cell fields.
        """
        V = _le(np.asarray(V, dtype=np.float64))
        fields = _fields(point_data, V.shape[0], "point")
        cell_fields = _fields(cell_data, self.n_cells, "cell")
        out = [self._header(V.shape[0], fields, cell_fields), np.uint64(V.nbytes).tobytes(),
               V.tobytes(), self._cell_bytes]
        for _, a, _ in fields + cell_fields:
            out += [np.uint64(a.nbytes).tobytes(), a.tobytes()]
        out.append(b"\n  </AppendedData>\n</VTKFile>\n")
        return out

    def write(self, path: PathLike, V: np.ndarray,
              point_data: Mapping[str, np.ndarray] | None = None,
              cell_data: Mapping[str, np.ndarray] | None = None) -> Path:
        """Write one frame to ``path`` atomically."""
        parts = self.parts(V, point_data, cell_data)

        def _write(p: Path) -> None:
            with open(p, "wb") as fh:
                fh.writelines(parts)

        return atomic_write(path, _write)


def _fields(data: Mapping[str, np.ndarray] | None, rows: int,
            kind: str) -> list[tuple[str, np.ndarray, int]]:
    """``(name, little-endian array, components)`` of each field, its rows checked."""
    fields = []
    for name, a in (data or {}).items():
        a = _le(np.asarray(a))
        if a.shape[0] != rows:
            raise ValueError(f"{kind} data {name!r} has {a.shape[0]} rows, expected {rows}")
        fields.append((str(name), a, int(np.prod(a.shape[1:], dtype=int))))
    return fields


class MeshioVtu:
    """VTU files by meshio's writer, compressed (the format fem3d wrote before 0.2).

    Parameters
    ----------
    faces : (n_faces, 3) int
        Triangles (0-based).
    compression : {"zlib", "lzma"}
        meshio's compression.
    """

    def __init__(self, faces: np.ndarray, compression: str) -> None:
        self.faces = check_faces(faces)
        self.compression = compression

    def write(self, path: PathLike, V: np.ndarray,
              point_data: Mapping[str, np.ndarray] | None = None) -> Path:
        """Write one frame to ``path`` atomically."""
        mesh = meshio.Mesh(V, [("triangle", self.faces)], point_data=dict(point_data or {}))
        return atomic_write(path, lambda p: meshio.vtu.write(p, mesh,
                                                            compression=self.compression))


class VtuWriter(NumberedFilesWriter):
    """Numbered VTU frames listed with their times in ``out_dir/frames.pvd`` (ParaView).

    Parameters
    ----------
    out_dir : str or PathLike
        Output folder (``frames/``, ``frames.pvd``, ``obstacles/``).
    faces : (n_faces, 3) int
        Triangles (0-based) of every frame.
    compression : {None, "zlib", "lzma"}
        ``None`` (the default): appended raw binary (:class:`RawVtu`, the triangles encoded
        once; about 1.5 ms and 1.5 MB per frame of the 26,002-vertex armadillo skin).
        ``"zlib"`` / ``"lzma"``: meshio's compressed writer (about 100 ms and 1.3 MB).
    index_every_frame : bool
        Rewrite ``frames.pvd`` after every frame (a ParaView session polling it sees each
        frame); ``False``: only by :meth:`write_index` (what the background writer does, at
        checkpoints, at the end and when idle: rewriting the list after each of 10,000
        frames would make a long run quadratic).
    digits, obstacles
        See :class:`~fem3d.io.frames.numbered.NumberedFilesWriter`.
    """

    fmt = "vtu"
    suffix = ".vtu"

    def __init__(self, out_dir: PathLike, faces: np.ndarray, *, compression: str | None = None,
                 index_every_frame: bool = True, digits: int = 5,
                 obstacles: Sequence[ObstacleMesh] = ()) -> None:
        self.compression = compression
        super().__init__(out_dir, faces, digits=digits, obstacles=obstacles)
        self.index_every_frame = bool(index_every_frame)
        self.pvd_path = self.out_dir / "frames.pvd"
        self._pvd_written: str | None = None

    def encoder(self, faces: np.ndarray) -> FileEncoder:
        """:class:`RawVtu`, or :class:`MeshioVtu` with a compression."""
        if self.compression is None:
            return RawVtu(faces)
        return MeshioVtu(faces, self.compression)

    def pvd_text(self) -> str:
        """ParaView collection listing every frame written so far, by time."""
        lines = [
            '<?xml version="1.0"?>',
            '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
            "  <Collection>",
        ]
        for step, (t, rel) in sorted(self.frames.items()):
            lines.append(f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(rel)}/>')
            for i in range(len(self.obstacles)):
                orel = self.obstacle_path(i, step).relative_to(self.out_dir).as_posix()
                lines.append(f'    <DataSet timestep="{t!r}" group="" part="{i + 1}" '
                             f'file={quoteattr(orel)}/>')
        lines += ["  </Collection>", "</VTKFile>", ""]
        return "\n".join(lines)

    def write_index(self) -> None:
        """Rewrite ``frames.pvd`` (atomically) if its list changed."""
        text = self.pvd_text()
        if text != self._pvd_written:
            atomic_write(self.pvd_path, text)
            self._pvd_written = text

    def restore(self, frames: Mapping[int, tuple[float, str]], step: int) -> None:
        """Continue a run (see the base class); ``frames.pvd`` is written again."""
        self._pvd_written = None
        super().restore(frames, step)


def _open(out_dir: PathLike, faces: np.ndarray, *, bodies: Bodies | None = None,
          dt: float = 1.0, obstacles: Sequence[ObstacleMesh] = ()) -> VtuWriter:
    return VtuWriter(out_dir, faces, obstacles=obstacles)


#: VTK XML unstructured grids and a ParaView collection.
FORMAT = FrameFormat(name="vtu", suffix=".vtu", open=_open, reads_back=True,
                     summary="frames/*.vtu + frames.pvd (ParaView)")

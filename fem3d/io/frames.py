"""Frame writers of a run: numbered surface frames for ParaView or Blender, or one USD stage.

- :class:`FrameWriter` - ``frames/frame_00042.vtu`` + ``frames.pvd`` (ParaView), or numbered
  OBJ files (Blender).
- :class:`UsdWriter` - ``frames.usdc``: a USD stage whose points come in chunks of frames
  (value clips in ``frames_clips/``), memory bounded, nothing rewritten.
- :class:`RawVtu` - VTK XML with appended raw binary data, the triangles encoded once.
- :func:`make_frame_writer` - the writer of a format name.

Every file is written atomically (:func:`fem3d.io.files.atomic_write`).
"""

from __future__ import annotations

import contextlib
import io
import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

import meshio
import numpy as np

from fem3d.errors import InputError, SimulationError
from fem3d.io.files import PathLike, atomic_write
from fem3d.io.obstacles import ObstacleMesh

__all__ = [
    "FrameWriter",
    "UsdWriter",
    "check_faces",
    "check_vertices",
    "make_frame_writer",
]


def check_faces(faces: np.ndarray) -> np.ndarray:
    F = np.asarray(faces)
    if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
        raise ValueError(f"faces must be an integer (f, 3) array, got {F.dtype} {F.shape}")
    if F.size and F.min() < 0:
        raise ValueError("faces hold a negative vertex index")
    return np.ascontiguousarray(F, dtype=np.int64)


def check_vertices(V: np.ndarray, faces: np.ndarray, step: int | None) -> np.ndarray:
    V = np.asarray(V, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"vertices must have shape (k, 3), got {V.shape}")
    if faces.size and faces.max() >= V.shape[0]:
        raise ValueError(f"faces reference vertex {int(faces.max())} but only {V.shape[0]} given")
    finite = np.isfinite(V).all(axis=1)
    if not finite.all():
        raise SimulationError(
            f"refusing to write non-finite coordinates (vertex {int(np.argmin(finite))})",
            step=step,
        )
    return V


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
        raise ValueError(f"point data {name!r}: cannot write dtype {a.dtype} to VTU")
    named = f" Name={quoteattr(name)}" if name is not None else ""
    comps = f' NumberOfComponents="{components}"' if components > 1 else ""
    return f'<DataArray type="{vtk}"{named}{comps} format="appended" offset="{offset}"/>'


class RawVtu:
    """VTK XML unstructured grids of one triangle mesh, appended raw binary data.

    The triangles (connectivity, offsets, cell types) are encoded once; a frame is the XML
    header, the positions' bytes (float64, exactly the values given) and the cells' bytes.
    No compression, no base64: writing a frame is a few ``memcpy`` and the file system's
    work. ParaView, VTK's ``vtkXMLUnstructuredGridReader`` and meshio read it.

    Parameters
    ----------
    faces : (n_faces, 3) int
        Triangles (0-based).
    """

    def __init__(self, faces: np.ndarray) -> None:
        F = check_faces(faces)
        idx = np.int32 if F.size == 0 or F.max() < 2**31 - 1 else np.int64
        self.n_cells = int(F.shape[0])
        self.cells = [  # (name, little-endian array)
            ("connectivity", _le(F.astype(idx).reshape(-1))),
            ("offsets", _le(np.arange(3, 3 * self.n_cells + 1, 3, dtype=idx))),
            ("types", np.full(self.n_cells, _VTK_TRIANGLE, dtype=np.uint8)),
        ]
        self._cell_bytes = b"".join(
            np.uint64(a.nbytes).tobytes() + a.tobytes() for _, a in self.cells)
        self._headers: dict[tuple, bytes] = {}

    def _header(self, n_points: int, fields: list[tuple[str, np.ndarray, int]]) -> bytes:
        key = (n_points, tuple((n, a.dtype.str, c) for n, a, c in fields))
        if key in self._headers:
            return self._headers[key]
        offset = 0
        points = _data_array(None, np.empty(0, "<f8"), offset, 3)
        offset += 8 + 24 * n_points
        cells = []
        for name, a in self.cells:
            cells.append(_data_array(name, a, offset, 1))
            offset += 8 + a.nbytes
        data = []
        for name, a, comps in fields:
            data.append(_data_array(name, a, offset, comps))
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
        lines += ["    </Piece>", "  </UnstructuredGrid>", '  <AppendedData encoding="raw">',
                  "   _"]
        header = "\n".join(lines).encode("ascii")
        if len(self._headers) < 8:
            self._headers[key] = header
        return header

    def parts(self, V: np.ndarray,
              point_data: Mapping[str, np.ndarray] | None = None) -> list[bytes]:
        """The file's bytes, in pieces (header, positions, cells, fields, end).

        Parameters
        ----------
        V : (n, 3) float64
            Positions.
        point_data : mapping of str to (n,) or (n, k) arrays, optional
            Extra per-vertex fields.
        """
        V = _le(np.asarray(V, dtype=np.float64))
        fields = []
        for name, a in (point_data or {}).items():
            a = _le(np.asarray(a))
            if a.shape[0] != V.shape[0]:
                raise ValueError(f"point data {name!r} has {a.shape[0]} rows, "
                                 f"expected {V.shape[0]}")
            fields.append((str(name), a, int(np.prod(a.shape[1:], dtype=int))))
        out = [self._header(V.shape[0], fields), np.uint64(V.nbytes).tobytes(), V.tobytes(),
               self._cell_bytes]
        for _, a, _ in fields:
            out += [np.uint64(a.nbytes).tobytes(), a.tobytes()]
        out.append(b"\n  </AppendedData>\n</VTKFile>\n")
        return out

    def write(self, path: PathLike, V: np.ndarray,
              point_data: Mapping[str, np.ndarray] | None = None) -> Path:
        """Write one frame to ``path`` atomically."""
        parts = self.parts(V, point_data)

        def _write(p: Path) -> None:
            with open(p, "wb") as fh:
                fh.writelines(parts)

        return atomic_write(path, _write)


class FrameWriter:
    """Numbered surface frames for ParaView (``vtu`` + ``.pvd``) or Blender (``obj``).

    Parameters
    ----------
    out_dir : str or PathLike
        Output folder; frames go to ``out_dir/frames/``, the ParaView collection to
        ``out_dir/frames.pvd``. Created if missing.
    faces : (n_faces, 3) int
        Triangles (0-based) of every frame.
    fmt : {"vtu", "obj"}
        ``"vtu"``: VTK XML unstructured grids listed with their times in ``frames.pvd``.
        ``"obj"``: plain Wavefront OBJ, 1-based faces (Blender's "import OBJ as sequence").
    digits : int
        Zero padding of the frame number (``frame_00042``).
    compression : {None, "zlib", "lzma"}
        ``None`` (the default): appended raw binary (:class:`RawVtu`, the triangles encoded
        once; about 1.5 ms and 1.5 MB per frame of the 26,002-vertex armadillo skin).
        ``"zlib"`` / ``"lzma"``: meshio's compressed writer (about 100 ms and 1.3 MB).
    pvd_every_frame : bool
        Rewrite ``frames.pvd`` after every frame (a ParaView session polling it sees each
        frame); ``False``: only by :meth:`write_pvd` (what the background writer does, at
        checkpoints, at the end and when idle: rewriting the list after each of 10,000
        frames would make a long run quadratic).

    Attributes
    ----------
    frames : dict[int, tuple[float, str]]
        step index -> (time, path relative to ``out_dir``) of every frame written.
    """

    def __init__(
        self,
        out_dir: PathLike,
        faces: np.ndarray,
        fmt: str = "vtu",
        *,
        digits: int = 5,
        compression: str | None = None,
        pvd_every_frame: bool = True,
        obstacles: Sequence[ObstacleMesh] = (),
    ) -> None:
        if fmt not in ("vtu", "obj"):
            raise ValueError(f"unknown frame format {fmt!r}; expected 'vtu' or 'obj'")
        self.out_dir = Path(out_dir)
        self.frame_dir = self.out_dir / "frames"
        self.frame_dir.mkdir(parents=True, exist_ok=True)
        self.faces = check_faces(faces)
        self.fmt = fmt
        self.digits = int(digits)
        self.compression = compression
        self.pvd_every_frame = bool(pvd_every_frame)
        self.frames: dict[int, tuple[float, str]] = {}
        self.pvd_path = self.out_dir / "frames.pvd" if fmt == "vtu" else None
        self._pvd_written: str | None = None
        self._raw = RawVtu(self.faces) if fmt == "vtu" and compression is None else None
        if fmt == "obj":
            buf = io.StringIO()
            np.savetxt(buf, self.faces + 1, fmt="f %d %d %d")
            self._obj_faces = buf.getvalue().encode("ascii")
        self.obstacles = tuple(obstacles)
        #: the obstacles' files, beside (not among) the bodies' frames
        self.obstacle_dir = self.out_dir / "obstacles"
        if self.obstacles:
            self.obstacle_dir.mkdir(parents=True, exist_ok=True)
        self._obstacle_writers = [FrameWriter._for_obstacle(self, ob) for ob in self.obstacles]
        self._static_written = False

    @staticmethod
    def _for_obstacle(parent: FrameWriter, ob: ObstacleMesh) -> FrameWriter:
        """A writer of one obstacle's files (no ``.pvd`` of its own)."""
        w = FrameWriter.__new__(FrameWriter)
        w.out_dir, w.frame_dir = parent.out_dir, parent.frame_dir
        w.faces, w.fmt, w.digits = check_faces(ob.faces), parent.fmt, parent.digits
        w.compression, w.pvd_every_frame, w.pvd_path = parent.compression, False, None
        w.frames, w._pvd_written, w.obstacles, w._obstacle_writers = {}, None, (), []
        w._static_written = True
        w._raw = RawVtu(w.faces) if parent._raw is not None else None
        if w.fmt == "obj":
            buf = io.StringIO()
            np.savetxt(buf, w.faces + 1, fmt="f %d %d %d")
            w._obj_faces = buf.getvalue().encode("ascii")
        return w

    def obstacle_path(self, i: int, step_index: int) -> Path:
        """File of obstacle ``i`` at frame ``step_index`` (one file for a static one)."""
        if self.obstacles[i].moving:
            return self.obstacle_dir / f"obstacle_{i}_{int(step_index):0{self.digits}d}.{self.fmt}"
        return self.obstacle_dir / f"obstacle_{i}.{self.fmt}"

    def _write_obstacles(self, step_index: int, t: float) -> None:
        for i, (ob, w) in enumerate(zip(self.obstacles, self._obstacle_writers, strict=True)):
            if ob.moving or not self._static_written:
                V = check_vertices(ob.positions(t), w.faces, step_index)
                w._write_file(self.obstacle_path(i, step_index), V, None)
        self._static_written = True

    def path_of(self, step_index: int) -> Path:
        """File of frame ``step_index``."""
        return self.frame_dir / f"frame_{int(step_index):0{self.digits}d}.{self.fmt}"

    def write(
        self,
        step_index: int,
        t: float,
        V: np.ndarray,
        point_data: Mapping[str, np.ndarray] | None = None,
    ) -> Path:
        """Write one frame.

        Parameters
        ----------
        step_index : int
            Frame number in the file name (usually the step index); writing the same index
            again replaces that frame.
        t : float
            Simulated time, listed in the ``.pvd``.
        V : (n_skin, 3) float64
            Vertex positions.
        point_data : mapping of str to (n_skin, ...) arrays, optional
            Extra per-vertex fields (``vtu`` only).

        Returns
        -------
        Path
            The frame file.

        Raises
        ------
        SimulationError
            ``V`` holds a non-finite coordinate (nothing is written).
        ValueError
            Wrong shapes.
        """
        step_index = int(step_index)
        V = check_vertices(V, self.faces, step_index)
        path = self.path_of(step_index)
        self._write_file(path, V, point_data)
        self._write_obstacles(step_index, t)
        self.frames[step_index] = (float(t), path.relative_to(self.out_dir).as_posix())
        if self.pvd_every_frame:
            self.write_pvd()
        return path

    def _write_file(self, path: Path, V: np.ndarray,
                    point_data: Mapping[str, np.ndarray] | None) -> None:
        if self._raw is not None:
            self._raw.write(path, V, point_data)
        elif self.fmt == "vtu":
            mesh = meshio.Mesh(V, [("triangle", self.faces)], point_data=dict(point_data or {}))
            atomic_write(path, lambda p: meshio.vtu.write(p, mesh, compression=self.compression))
        else:
            # one % over every coordinate: np.savetxt's text, in half its time
            text = ("v %.9g %.9g %.9g\n" * V.shape[0]) % tuple(V.ravel().tolist())
            atomic_write(path, text.encode("ascii") + self._obj_faces)

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

    def write_pvd(self) -> None:
        """Rewrite ``frames.pvd`` (atomically) if its list changed (``vtu`` only)."""
        if self.pvd_path is None:
            return
        text = self.pvd_text()
        if text != self._pvd_written:
            atomic_write(self.pvd_path, text)
            self._pvd_written = text

    # -- what the run loop calls on every writer (the USD writer works otherwise) --------
    def flush(self) -> None:
        """Every frame is on disk once :meth:`write` returns; bring ``frames.pvd`` up to
        date."""
        self.write_pvd()

    def close(self) -> None:
        """Same as :meth:`flush`."""
        self.flush()

    def restore(self, frames: Mapping[int, tuple[float, str]], step: int) -> None:
        """Continue a run: the frames written up to ``step`` (a checkpoint's list); files of
        later frames (written after the checkpoint by an interrupted run) are removed."""
        self.frames = {int(k): (float(t), str(r)) for k, (t, r) in frames.items()}
        for folder, pattern in ((self.frame_dir, f"frame_*.{self.fmt}"),
                                (self.obstacle_dir, f"obstacle_*_*.{self.fmt}")):
            for f in folder.glob(pattern):
                with contextlib.suppress(ValueError):
                    if int(f.stem.split("_")[-1]) > step:
                        f.unlink()
        self._static_written = False  # written again with the next frame
        self._pvd_written = None
        self.write_pvd()

    def read_frames(self, stride: int = 1) -> Iterator[tuple[int, np.ndarray]]:
        """``(step, (n_skin, 3) vertices)`` of every ``stride``-th frame listed, read back
        from disk."""
        for step in sorted(self.frames)[::max(1, int(stride))]:
            with contextlib.suppress(Exception):
                yield step, meshio.read(self.out_dir / self.frames[step][1]).points


def _prim_names(names: Sequence[str]) -> list[str]:
    out: list[str] = []
    for name in names:
        n = re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "body"
        if n[0].isdigit():
            n = "_" + n
        base, k = n, 1
        while n in out:
            k += 1
            n = f"{base}_{k}"
        out.append(n)
    return out


#: Folder of the USD writer's layers, beside ``frames.usdc``.
USD_CLIP_DIR = "frames_clips"


class UsdWriter:
    """A USD stage of a run, written in chunks: memory bounded, nothing on disk rewritten.

    ``frames.usdc`` is a small root layer: stage metadata (``timeCodesPerSecond = 1 / dt``,
    start and end time code, Y up) and USD *value clips* on ``/World``. Beside it, in
    ``frames_clips/``:

    * ``mesh.usdc`` - the ``/World/<body>`` ``UsdGeom.Mesh`` prims with their triangles,
      written once (a sublayer of the root);
    * ``manifest.usda`` - the clip manifest (the ``points`` attributes the clips hold);
    * ``clip_00000.usdc``, ``clip_00100.usdc``, ... - the ``points`` of a chunk of frames at
      time code = step index (float32), named by their first step.

    A chunk is written once it holds ``chunk_frames`` frames (or ``chunk_bytes``), and by
    :meth:`flush` (checkpoints, the end of a run); only the root layer (a list of clips) is
    rewritten then. Memory stays at one chunk and the time per frame is constant, however
    long the run. Blender, Houdini and usdview open ``frames.usdc`` directly (value clips
    are how long animated caches are written).

    Parameters
    ----------
    out_dir : path
    faces : (n_faces, 3) int
        Triangles of the whole display mesh.
    bodies : list of (name, vertex slice, face slice)
        Each body's part of the display mesh.
    dt : float
        Time step (seconds per time code).
    chunk_frames : int
        Frames per clip at most.
    chunk_bytes : int
        Bytes of points per clip at most (a chunk of a big mesh holds fewer frames).
    obstacles : sequence of ObstacleMesh, optional
        The contact scene's obstacles: a ``/World/obstacle_<i>`` mesh prim each, its points
        in ``mesh.usdc`` when static, in the clips (every frame) when moving.
    """

    fmt = "usd"

    def __init__(self, out_dir: PathLike, faces: np.ndarray,
                 bodies: Sequence[tuple[str, slice, slice]], dt: float, *,
                 chunk_frames: int = 100, chunk_bytes: int = 64 << 20,
                 obstacles: Sequence[ObstacleMesh] = ()) -> None:
        from pxr import Usd  # noqa: F401 - usd-core is optional: fail early without it

        self.out_dir = Path(out_dir)
        self.path = self.out_dir / "frames.usdc"
        self.clip_dir = self.out_dir / USD_CLIP_DIR
        self.clip_dir.mkdir(parents=True, exist_ok=True)
        self.faces = check_faces(faces)
        self.bodies = [(n, vs, fs) for n, vs, fs in bodies]
        self.obstacles = tuple(obstacles)
        names = _prim_names([b[0] for b in bodies]
                            + [f"obstacle_{i}" for i in range(len(self.obstacles))])
        self.names = names[: len(self.bodies)]
        self.obstacle_names = names[len(self.bodies):]
        self._moving = [i for i, ob in enumerate(self.obstacles) if ob.moving]
        self._chunk_obstacles: dict[int, list[np.ndarray]] = {}
        self.dt = float(dt)
        n = max(vs.stop for _, vs, _ in self.bodies)
        self.chunk_frames = max(1, min(int(chunk_frames), int(chunk_bytes) // max(1, 12 * n)))
        self.frames: dict[int, tuple[float, str]] = {}
        self.clips: list[tuple[int, int, str]] = []  # (first step, last step, rel path)
        self._chunk: dict[int, np.ndarray] = {}
        self.pvd_path = None
        self.frame_dir = self.out_dir
        self._mesh_written = False

    def _clip_rel(self, first: int) -> str:
        return f"{USD_CLIP_DIR}/clip_{first:05d}.usdc"

    def write(self, step_index: int, t: float, V: np.ndarray, point_data=None) -> Path:
        """Add one frame to the current chunk (written when full or by :meth:`flush`)."""
        step_index = int(step_index)
        V = check_vertices(V, self.faces, step_index)
        if self._chunk and step_index <= max(self._chunk):
            self._write_chunk()  # frames go forward in a clip (a step written again)
        self._chunk[step_index] = np.asarray(V, dtype=np.float32).copy()
        if self._moving:
            self._chunk_obstacles[step_index] = [
                np.asarray(self.obstacles[i].positions(t), dtype=np.float32)
                for i in self._moving]
        first = min(self._chunk)
        self.frames[step_index] = (float(t), self._clip_rel(first))
        if len(self._chunk) >= self.chunk_frames:
            self._write_chunk()
        return self.path

    def flush(self) -> None:
        """Write the current chunk (if any) and the root layer listing every clip."""
        if self._chunk:
            self._write_chunk()

    def close(self) -> None:
        """Same as :meth:`flush`."""
        self.flush()

    def _write_chunk(self) -> None:
        from pxr import Sdf, Vt  # usd-core is optional (fem3d[scenes])

        steps = sorted(self._chunk)
        rel = self._clip_rel(steps[0])
        layer = Sdf.Layer.CreateAnonymous(".usdc")
        for name, (_, vs, _) in zip(self.names, self.bodies, strict=True):
            attr = self._points_spec(layer, name)
            for s in steps:
                layer.SetTimeSample(attr.path, float(s), Vt.Vec3fArray.FromNumpy(
                    np.ascontiguousarray(self._chunk[s][vs])))
        for k, i in enumerate(self._moving):
            attr = self._points_spec(layer, self.obstacle_names[i])
            for s in steps:
                layer.SetTimeSample(attr.path, float(s), Vt.Vec3fArray.FromNumpy(
                    np.ascontiguousarray(self._chunk_obstacles[s][k])))
        atomic_write(self.out_dir / rel, lambda p: layer.Export(str(p)))
        self.clips = [c for c in self.clips if c[2] != rel] + [(steps[0], steps[-1], rel)]
        self._chunk = {}
        self._chunk_obstacles = {}
        self._write_root()

    def _points_spec(self, layer, name: str):
        from pxr import Sdf  # usd-core is optional (fem3d[scenes])

        world = layer.GetPrimAtPath("/World") or Sdf.PrimSpec(layer, "World", Sdf.SpecifierDef,
                                                              "Xform")
        prim = Sdf.PrimSpec(world, name, Sdf.SpecifierDef, "Mesh")
        return Sdf.AttributeSpec(prim, "points", Sdf.ValueTypeNames.Point3fArray)

    def _write_static(self) -> None:
        """``mesh.usdc`` (the prims and their triangles) and the clip manifest, once."""
        from pxr import Sdf, Usd, UsdGeom, Vt  # usd-core is optional (fem3d[scenes])

        stage = Usd.Stage.CreateInMemory()
        UsdGeom.Xform.Define(stage, "/World")
        for name, (_, vs, fs) in zip(self.names, self.bodies, strict=True):
            mesh = UsdGeom.Mesh.Define(stage, Sdf.Path(f"/World/{name}"))
            F = self.faces[fs] - vs.start
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(
                np.full(F.shape[0], 3, dtype=np.int32)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(
                np.ascontiguousarray(F.reshape(-1), dtype=np.int32)))
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        for i, (name, ob) in enumerate(zip(self.obstacle_names, self.obstacles, strict=True)):
            mesh = UsdGeom.Mesh.Define(stage, Sdf.Path(f"/World/{name}"))
            F = check_faces(ob.faces)
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(
                np.full(F.shape[0], 3, dtype=np.int32)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(
                np.ascontiguousarray(F.reshape(-1), dtype=np.int32)))
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            mesh.GetPrim().SetCustomDataByKey("fem3d:name", ob.name)
            if i not in self._moving:
                mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(
                    np.ascontiguousarray(ob.positions(0.0), dtype=np.float32)))
        layer = stage.GetRootLayer()
        atomic_write(self.clip_dir / "mesh.usdc", lambda p: layer.Export(str(p)))
        manifest = Sdf.Layer.CreateAnonymous(".usda")
        for name in self.names + [self.obstacle_names[i] for i in self._moving]:
            self._points_spec(manifest, name)
        atomic_write(self.clip_dir / "manifest.usda", lambda p: manifest.Export(str(p)))
        self._mesh_written = True

    def _write_root(self) -> None:
        """``frames.usdc``: stage metadata and the clips on ``/World`` (atomically)."""
        from pxr import Gf, Sdf, Vt  # usd-core is optional (fem3d[scenes])

        if not self._mesh_written:
            self._write_static()
        layer = Sdf.Layer.CreateAnonymous(".usdc")
        layer.subLayerPaths.append(f"./{USD_CLIP_DIR}/mesh.usdc")
        root = layer.pseudoRoot
        root.SetInfo("upAxis", "Y")
        root.SetInfo("metersPerUnit", 1.0)
        clips = sorted(self.clips)
        if clips:
            layer.startTimeCode, layer.endTimeCode = float(clips[0][0]), float(clips[-1][1])
        layer.timeCodesPerSecond = layer.framesPerSecond = 1.0 / self.dt
        layer.defaultPrim = "World"
        world = Sdf.PrimSpec(layer, "World", Sdf.SpecifierOver)
        times = sorted({float(x) for a, b, _ in clips for x in (a, b)})
        world.SetInfo("clips", {"default": {
            "primPath": "/World",
            "manifestAssetPath": Sdf.AssetPath(f"./{USD_CLIP_DIR}/manifest.usda"),
            "assetPaths": Sdf.AssetPathArray([f"./{rel}" for _, _, rel in clips]),
            "active": Vt.Vec2dArray([Gf.Vec2d(a, i) for i, (a, _, _) in enumerate(clips)]),
            "times": Vt.Vec2dArray([Gf.Vec2d(x, x) for x in times]),
        }})
        atomic_write(self.path, lambda p: layer.Export(str(p)))

    def restore(self, frames: Mapping[int, tuple[float, str]], step: int) -> None:
        """Continue a run: the clips of the frames up to ``step`` (a checkpoint's list);
        clips written after the checkpoint are removed, the root layer rewritten. A stage
        of an older fem3d (every frame in ``frames.usdc``) is moved into clips first."""
        kept = {int(k): (float(t), str(r)) for k, (t, r) in frames.items() if int(k) <= step}
        self._chunk = {}
        self._chunk_obstacles = {}
        if any(r == self.path.name for _, r in kept.values()):
            kept = self._from_single_stage(kept)
        self.frames = kept
        by_clip: dict[str, list[int]] = {}
        for s, (_, rel) in kept.items():
            by_clip.setdefault(rel, []).append(s)
        for rel in by_clip:
            if not (self.out_dir / rel).is_file():
                raise InputError(f"{rel} is missing (the checkpoint lists frames in it)",
                                 path=self.out_dir / rel)
        self.clips = sorted((min(v), max(v), rel) for rel, v in by_clip.items())
        for f in self.clip_dir.glob("clip_*.usdc"):
            if f"{USD_CLIP_DIR}/{f.name}" not in by_clip:
                f.unlink()
        if self.clips:
            self._write_root()

    def _from_single_stage(self, kept: dict[int, tuple[float, str]]
                           ) -> dict[int, tuple[float, str]]:
        """Frames of a ``frames.usdc`` with time samples (fem3d < 0.2) into clips."""
        from pxr import Usd, UsdGeom  # usd-core is optional (fem3d[scenes])

        if not self.path.is_file():
            raise InputError("frames.usdc is missing (the checkpoint lists frames in it)",
                             path=self.path)
        stage = Usd.Stage.Open(str(self.path))
        attrs = [UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{name}")).GetPointsAttr()
                 for name in self.names]
        n = max(vs.stop for _, vs, _ in self.bodies)
        for s in sorted(kept):
            V = np.zeros((n, 3), dtype=np.float64)
            for attr, (_, vs, _) in zip(attrs, self.bodies, strict=True):
                V[vs] = np.asarray(attr.Get(Usd.TimeCode(s)), dtype=np.float64)
            self.write(s, kept[s][0], V)
        del stage
        self.flush()
        return dict(self.frames)

    def read_frames(self, stride: int = 1) -> Iterator[tuple[int, np.ndarray]]:
        """``(step, vertices)`` of every ``stride``-th frame listed, read back from disk."""
        from pxr import Usd, UsdGeom  # usd-core is optional (fem3d[scenes])

        self.flush()
        if not self.frames:
            return
        stage = Usd.Stage.Open(str(self.path))
        attrs = [UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{name}")).GetPointsAttr()
                 for name in self.names]
        n = max(vs.stop for _, vs, _ in self.bodies)
        for s in sorted(self.frames)[::max(1, int(stride))]:
            V = np.zeros((n, 3), dtype=np.float64)
            for attr, (_, vs, _) in zip(attrs, self.bodies, strict=True):
                V[vs] = np.asarray(attr.Get(Usd.TimeCode(s)), dtype=np.float64)
            yield s, V


def make_frame_writer(out_dir: PathLike, faces: np.ndarray, fmt: str, *,
                      bodies: Sequence[tuple[str, slice, slice]] | None = None,
                      dt: float = 1.0, obstacles: Sequence[ObstacleMesh] = ()
                      ) -> FrameWriter | UsdWriter:
    """The frame writer of a format: ``"vtu"``/``"obj"`` (:class:`FrameWriter`) or ``"usd"``
    (:class:`UsdWriter`, one prim per entry of ``bodies``), with the ``obstacles``' meshes."""
    if fmt == "usd":
        if bodies is None:  # one prim; its points: the vertices the faces use, and below
            bodies = [("body", slice(0, int(np.max(faces)) + 1), slice(0, len(faces)))]
        return UsdWriter(out_dir, faces, bodies, dt, obstacles=obstacles)
    return FrameWriter(out_dir, faces, fmt, obstacles=obstacles)

"""A USD stage of a run: ``frames.usdc`` whose points come in chunks of frames (value clips).

- :class:`UsdWriter` - the stage, written in chunks (memory bounded, nothing rewritten).
- :data:`FORMAT` - the ``"usd"`` output format (needs usd-core, module ``pxr``).
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import PathLike, atomic_write
from fem3d.io.frames.base import Bodies, FrameFormat, check_faces, check_vertices, whole_mesh
from fem3d.io.obstacles import ObstacleMesh

__all__ = ["FORMAT", "USD_CLIP_DIR", "UsdWriter"]


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
                 bodies: Bodies, dt: float, *,
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


def _open(out_dir: PathLike, faces: np.ndarray, *, bodies: Bodies | None = None,
          dt: float = 1.0, obstacles: Sequence[ObstacleMesh] = ()) -> UsdWriter:
    return UsdWriter(out_dir, faces, whole_mesh(faces, bodies), dt, obstacles=obstacles)


#: One USD stage, a prim per body and per obstacle.
FORMAT = FrameFormat(name="usd", suffix=".usdc", open=_open, extra="pxr",
                     summary="frames.usdc, value clips (Blender, Houdini, usdview)")

"""Frame output that keeps up: VTU as appended raw binary, the writer thread, USD value clips.

* the raw VTU frames read back in meshio (and VTK's own reader when ``vtk`` is installed) with
  exactly the positions given, byte for byte the same files on every run;
* :class:`~fem3d.io.framequeue.BackgroundWriter`: the same files as writing in the caller's
  thread whatever the timing, the writer's error raised in the caller with the file's name,
  nothing written after a lost frame, a flush that waits for every frame;
* :class:`~fem3d.io.frames.UsdWriter`: chunks of frames as value clips composed by
  ``frames.usdc`` (read back with ``pxr``), files never rewritten, resume appending chunks.
"""

from __future__ import annotations

import errno
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.app.run import run_scene
from fem3d.errors import SimulationError
from fem3d.io.framequeue import BackgroundWriter
from fem3d.io.frames import NumberedFilesWriter, ObjWriter, RawVtu, UsdWriter, VtuWriter
from fem3d.scene import apply_overrides, load_scene
from tests.io.test_outputs import torus

ROOT = Path(__file__).resolve().parents[2]
ARMA = str(ROOT / "data" / "arma_6.node")  # 259 vertices, no skin: cheap frames


def _frames(n: int, seed: int = 0) -> list[np.ndarray]:
    V, _ = torus()
    rng = np.random.default_rng(seed)
    return [V + 0.01 * k + rng.normal(scale=1e-3, size=V.shape) for k in range(n)]


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------------- raw VTU


def test_raw_vtu_reads_back_in_meshio(tmp_path):
    import meshio

    _, F = torus()
    frames = _frames(3)
    fw = VtuWriter(tmp_path, F)  # the default: appended raw binary
    for k, V in enumerate(frames):
        fw.write(k, 0.01 * k, V, point_data={"speed": np.linalg.norm(V, axis=1)} if k == 2
                 else None)
    head = fw.path_of(0).read_bytes()[:2000]
    assert b'<AppendedData encoding="raw">' in head and b"compressor" not in head
    for k, V in enumerate(frames):
        m = meshio.read(fw.path_of(k))
        np.testing.assert_array_equal(m.points, V)  # float64, exactly the values given
        np.testing.assert_array_equal(m.cells_dict["triangle"], F)
    np.testing.assert_array_equal(meshio.read(fw.path_of(2)).point_data["speed"],
                                  np.linalg.norm(frames[2], axis=1))
    # the same positions as meshio's own (compressed) writer, the format used before
    old = VtuWriter(tmp_path / "old", F, compression="zlib")
    old.write(1, 0.01, frames[1])
    np.testing.assert_array_equal(meshio.read(old.path_of(1)).points,
                                  meshio.read(fw.path_of(1)).points)


def test_raw_vtu_reads_back_in_vtk(tmp_path):
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    V, F = torus()
    path = RawVtu(F).write(tmp_path / "f.vtu", V)
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    grid = reader.GetOutput()
    np.testing.assert_array_equal(vtk_to_numpy(grid.GetPoints().GetData()), V)
    assert grid.GetNumberOfCells() == len(F)


def test_raw_vtu_bytes_are_fixed():
    """The header and the cells do not depend on the positions: a frame is the same bytes
    for the same positions, and only the positions' bytes change between frames."""
    V, F = torus()
    raw = RawVtu(F)
    a, b = raw.parts(V), raw.parts(V + 1.0)
    assert b"".join(a) == b"".join(RawVtu(F).parts(V))
    assert [x == y for x, y in zip(a, b, strict=True)] == [True, True, False, True, True]


# ----------------------------------------------------------------------------- the thread


#: The numbered-file writers by format.
_WRITERS: dict[str, type[NumberedFilesWriter]] = {"vtu": VtuWriter, "obj": ObjWriter}


class _SlowWrites:
    """Mixed into a frame writer: writes that take a random while (thread timing varies)."""

    def __init__(self, *args, seed: int = 0, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.rng = np.random.default_rng(seed)

    def write(self, step_index, t, V, point_data=None):  # noqa: ANN001, ANN201
        time.sleep(float(self.rng.uniform(0.0, 0.004)))
        return super().write(step_index, t, V, point_data)


def _slow_writer(fmt: str, *args, seed: int) -> NumberedFilesWriter:
    """A ``fmt`` writer with :class:`_SlowWrites`."""
    return type(f"Slow_{fmt}", (_SlowWrites, _WRITERS[fmt]), {})(*args, seed=seed)


@pytest.mark.parametrize("fmt", ["vtu", "obj"])
def test_background_writer_same_bytes_whatever_the_timing(tmp_path, fmt):
    _, F = torus()
    frames = _frames(12)
    direct = _WRITERS[fmt](tmp_path / "direct", F)
    for k, V in enumerate(frames):
        direct.write(2 * k, 0.02 * k, V)
    for seed, depth in ((1, 1), (2, 3), (3, 64)):
        bg = BackgroundWriter(_slow_writer(fmt, tmp_path / f"bg{seed}", F, seed=seed),
                              depth=depth, index_seconds=0.0)
        for k, V in enumerate(frames):
            bg.write(2 * k, 0.02 * k, V)
            if seed == 2 and k == 5:
                bg.flush()
        bg.close()
        assert not bg._thread.is_alive()
        assert _tree(tmp_path / f"bg{seed}") == _tree(tmp_path / "direct"), (seed, depth)
        assert bg.frames == direct.frames


def test_background_writer_copies_and_refuses_non_finite_at_once(tmp_path):
    V, F = torus()
    bg = BackgroundWriter(VtuWriter(tmp_path, F))
    W = V.copy()
    bg.write(0, 0.0, W)
    W += 5.0  # changed after the call: the frame keeps what was given
    bad = V.copy()
    bad[3, 0] = np.nan
    with pytest.raises(SimulationError) as exc:
        bg.write(1, 0.01, bad)
    assert exc.value.step == 1
    bg.close()
    import meshio

    np.testing.assert_array_equal(meshio.read(tmp_path / "frames" / "frame_00000.vtu").points, V)
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["frame_00000.vtu"]


def test_background_writer_error_surfaces_with_the_file_and_stops(tmp_path, monkeypatch):
    _, F = torus()
    fw = VtuWriter(tmp_path, F)
    real = VtuWriter.write
    calls = []

    def write(self, step_index, t, V, point_data=None):  # noqa: ANN001, ANN202
        calls.append(step_index)
        if step_index == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC) + " while writing",
                          str(self.path_of(step_index)))
        return real(self, step_index, t, V, point_data)

    monkeypatch.setattr(VtuWriter, "write", write)
    bg = BackgroundWriter(fw, depth=64)
    frames = _frames(8)
    with pytest.raises(OSError) as exc:
        for k, V in enumerate(frames):
            bg.write(k, 0.01 * k, V)
        bg.flush()
    assert "frame_00003.vtu" in str(exc.value) and exc.value.errno == errno.ENOSPC
    with pytest.raises(OSError):  # raised again, never a checkpoint after a lost frame
        bg.flush()
    bg.abandon()
    assert not bg._thread.is_alive()
    assert calls == [0, 1, 2, 3]  # nothing written after the lost frame
    assert sorted(fw.frames) == [0, 1, 2]


def test_background_writer_waits_only_when_full(tmp_path):
    _, F = torus()
    gate = threading.Event()

    class Gated(VtuWriter):
        def write(self, *args, **kwargs):  # noqa: ANN002, ANN003, ANN201
            gate.wait()
            return super().write(*args, **kwargs)

    bg = BackgroundWriter(Gated(tmp_path, F), depth=4)
    frames = _frames(4)
    for k, V in enumerate(frames[:4]):  # the thread holds one, the queue takes the rest
        bg.write(k, 0.01 * k, V)
    assert bg.waited_seconds == 0.0  # (no wall-time bound: it would depend on the load)
    main_id = threading.get_ident()

    def open_gate_once_blocked() -> None:
        # the gate opens 0.2 s after the writer is seen blocked in Queue.put (not after a
        # fixed delay from here, which a loaded machine could overtake)
        deadline = time.monotonic() + 60.0  # a writer that never blocks: open anyway
        while time.monotonic() < deadline:
            f = sys._current_frames().get(main_id)
            names = set()
            while f is not None:
                names.add(f.f_code.co_name)
                f = f.f_back
            if "put" in names and "write" in names:
                break
            time.sleep(0.005)
        time.sleep(0.2)
        gate.set()

    threading.Thread(target=open_gate_once_blocked, daemon=True).start()
    bg.write(4, 0.04, frames[0])
    bg.write(5, 0.05, frames[1])  # the queue is full until the gate opens
    assert bg.waited_seconds > 0.05
    bg.close()
    assert sorted(bg.frames) == list(range(6))


# ----------------------------------------------------------------------------- USD clips


def _usd_points(path: Path, prim: str = "/World/body"):
    """The composed stage (kept alive by the caller), its points' time samples and
    attribute."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath(prim)).GetPointsAttr()
    return stage, attr.GetTimeSamples(), attr


def test_usd_clips_compose_and_are_never_rewritten(tmp_path):
    V, F = torus()
    frames = _frames(11)
    w = UsdWriter(tmp_path, F, [("body", slice(0, len(V)), slice(0, len(F)))], dt=0.01,
                  chunk_frames=4)
    seen: dict[str, int] = {}
    for k, W in enumerate(frames):
        w.write(2 * k, 0.02 * k, W)
        for p in (tmp_path / "frames_clips").glob("clip_*.usdc"):
            seen.setdefault(p.name, p.stat().st_mtime_ns)
            assert p.stat().st_mtime_ns == seen[p.name], f"{p.name} rewritten"
        assert len(w._chunk) < 4  # memory: one chunk at most
    w.flush()
    assert sorted(seen) == ["clip_00000.usdc", "clip_00008.usdc"]  # + the flushed one:
    assert sorted(p.name for p in (tmp_path / "frames_clips").iterdir()) == [
        "clip_00000.usdc", "clip_00008.usdc", "clip_00016.usdc", "manifest.usda", "mesh.usdc"]
    stage, times, attr = _usd_points(tmp_path / "frames.usdc")
    assert times == [2.0 * k for k in range(11)]
    for k in (0, 3, 4, 10):
        np.testing.assert_allclose(np.asarray(attr.Get(2.0 * k)), frames[k], atol=1e-6)
    from pxr import UsdGeom

    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 20.0)
    assert stage.GetTimeCodesPerSecond() == pytest.approx(100.0)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/body"))
    np.testing.assert_array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()),
                                  F.reshape(-1))
    assert stage.GetDefaultPrim().GetPath() == "/World"


def test_usd_run_resume_appends_clips(tmp_path):
    s = apply_overrides(load_scene(ARMA, {"output.format": "usd", "simulation.steps": 9}), {})
    out = tmp_path / "o"
    summary = run_scene(s, out, checkpoint_every=4)
    assert summary.status == "ok"
    whole = tmp_path / "whole"
    assert run_scene(apply_overrides(s, {"simulation.steps": 15}), whole).status == "ok"
    clips = sorted(p.name for p in (out / "frames_clips").glob("clip_*.usdc"))
    before = {n: (out / "frames_clips" / n).read_bytes() for n in clips}
    assert clips == ["clip_00000.usdc", "clip_00005.usdc", "clip_00009.usdc"]
    assert main(["resume", str(out), "--steps", "15", "--quiet", "--no-preview"]) == 0
    for n, data in before.items():  # what was on disk is still there, unchanged
        assert (out / "frames_clips" / n).read_bytes() == data
    stage, times, attr = _usd_points(out / "frames.usdc", "/World/arma_6")
    assert times == [float(i) for i in range(16)]
    ref_stage, _, ref = _usd_points(whole / "frames.usdc", "/World/arma_6")
    for t in (0.0, 4.0, 9.0, 10.0, 15.0):
        np.testing.assert_array_equal(np.asarray(attr.Get(t)), np.asarray(ref.Get(t)))

"""Tests of fem3d.io: atomic writes, frames, energy log, GIF preview, checkpoints."""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageSequence

from fem3d.errors import InputError, SimulationError
from fem3d.io.checkpoint import load_checkpoint, save_checkpoint
from fem3d.io.energy import EnergyLog, read_energy_csv
from fem3d.io.files import atomic_path, atomic_write
from fem3d.io.frames import ObjWriter, VtuWriter, make_frame_writer
from fem3d.io.preview import _cluster_decimate, plot_energy, render_preview


def torus(nu: int = 24, nv: int = 12, R: float = 1.0, r: float = 0.35):
    """Closed, consistently oriented triangulated torus (y is the symmetry axis)."""
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    U, Vv = np.meshgrid(u, v, indexing="ij")
    V = np.stack(
        [(R + r * np.cos(Vv)) * np.cos(U), r * np.sin(Vv), (R + r * np.cos(Vv)) * np.sin(U)],
        axis=-1,
    ).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = i * nv + j
    b = ((i + 1) % nu) * nv + j
    c = ((i + 1) % nu) * nv + (j + 1) % nv
    d = i * nv + (j + 1) % nv
    F = np.concatenate([np.stack([a, c, b], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    return V, F


def _listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# ----------------------------------------------------------------------------- atomic


def test_atomic_write_bytes_text_callable(tmp_path):
    atomic_write(tmp_path / "a.bin", b"\x00\x01")
    atomic_write(tmp_path / "b.txt", "héllo")
    atomic_write(tmp_path / "c.dat", lambda p: Path(p).write_bytes(b"xyz"))
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01"
    assert (tmp_path / "b.txt").read_text(encoding="utf-8") == "héllo"
    assert (tmp_path / "c.dat").read_bytes() == b"xyz"
    assert _listing(tmp_path) == ["a.bin", "b.txt", "c.dat"]
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "a.bin").stat().st_mode & 0o777 == 0o666 & ~umask


def test_failing_writer_leaves_old_file_and_no_temp(tmp_path):
    target = tmp_path / "energy.csv"
    target.write_text("old complete content\n")

    def bad_writer(p: Path) -> None:
        with open(p, "w") as fh:
            fh.write("half a fi")
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError, match="disk on fire"):
        atomic_write(target, bad_writer)
    assert target.read_text() == "old complete content\n"
    assert _listing(tmp_path) == ["energy.csv"]
    # same when the target did not exist yet
    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "new.csv", bad_writer)
    assert _listing(tmp_path) == ["energy.csv"]
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(tmp_path / "k.txt") as p:
            p.write_text("partial")
            raise KeyboardInterrupt
    assert _listing(tmp_path) == ["energy.csv"]


def test_atomic_write_rejects_other_types(tmp_path):
    with pytest.raises(TypeError):
        atomic_write(tmp_path / "x", 42)  # type: ignore[arg-type]
    assert _listing(tmp_path) == []


# ----------------------------------------------------------------------------- frames


@pytest.mark.parametrize("compression", ["zlib", None])
def test_frame_writer_vtu_and_pvd(tmp_path, compression):
    import meshio

    V, F = torus()
    fw = VtuWriter(tmp_path / "run", F, compression=compression)
    times = [0.0, 0.01, 0.02, 0.03]
    for k, t in enumerate(times):
        fw.write(k, t, V * (1 + k))
    frames_dir = tmp_path / "run" / "frames"
    assert _listing(frames_dir) == [f"frame_{k:05d}.vtu" for k in range(4)]
    assert _listing(tmp_path / "run") == ["frames", "frames.pvd"]
    root = ET.parse(tmp_path / "run" / "frames.pvd").getroot()
    assert root.get("type") == "Collection"
    ds = root.findall("./Collection/DataSet")
    assert [float(d.get("timestep")) for d in ds] == times
    assert [d.get("file") for d in ds] == [f"frames/frame_{k:05d}.vtu" for k in range(4)]
    m = meshio.read(frames_dir / "frame_00002.vtu")
    np.testing.assert_array_equal(m.points, V * 3)
    np.testing.assert_array_equal(m.cells_dict["triangle"], F)
    # rewriting a step replaces the frame and keeps one pvd entry
    fw.write(2, 0.02, V)
    assert len(ET.parse(tmp_path / "run" / "frames.pvd").getroot().findall(".//DataSet")) == 4
    np.testing.assert_array_equal(meshio.read(frames_dir / "frame_00002.vtu").points, V)


def test_frame_writer_refuses_non_finite(tmp_path):
    V, F = torus()
    fw = VtuWriter(tmp_path, F)
    fw.write(0, 0.0, V)
    pvd_before = (tmp_path / "frames.pvd").read_text()
    bad = V.copy()
    bad[5, 1] = np.nan
    with pytest.raises(SimulationError) as exc:
        fw.write(1, 0.01, bad)
    assert exc.value.step == 1
    bad[5, 1] = np.inf
    with pytest.raises(SimulationError):
        fw.write(1, 0.01, bad)
    assert _listing(tmp_path / "frames") == ["frame_00000.vtu"]
    assert (tmp_path / "frames.pvd").read_text() == pvd_before
    with pytest.raises(ValueError):
        fw.write(1, 0.01, V[:10])  # faces reference missing vertices
    with pytest.raises(ValueError):
        make_frame_writer(tmp_path, F, "stl")


def test_frame_writer_obj(tmp_path):
    V, F = torus(8, 6)
    fw = ObjWriter(tmp_path, F)
    fw.write(7, 0.07, V)
    path = tmp_path / "frames" / "frame_00007.obj"
    assert _listing(tmp_path / "frames") == ["frame_00007.obj"]
    assert not (tmp_path / "frames.pvd").exists()
    lines = path.read_text().splitlines()
    v = np.array([ln.split()[1:] for ln in lines if ln.startswith("v ")], dtype=float)
    f = np.array([ln.split()[1:] for ln in lines if ln.startswith("f ")], dtype=int)
    np.testing.assert_allclose(v, V, rtol=1e-8, atol=1e-12)
    np.testing.assert_array_equal(f, F + 1)


# ----------------------------------------------------------------------------- energy


def test_energy_csv_round_trip_and_plot(tmp_path):
    rng = np.random.default_rng(0)
    log = EnergyLog(tmp_path / "energy.csv")
    rows = rng.normal(size=(50, 3)) * np.array([1, 1e8, 1e-9])
    t = np.arange(50) * 0.01
    for ti, (k, p, _) in zip(t, rows, strict=True):
        log.append(ti, k, p)
    log.append(0.5, 1.0, 2.0, total=3.5)
    assert len(log) == 51
    log.write()
    text = (tmp_path / "energy.csv").read_text()
    assert text.splitlines()[0] == "t,kinetic,potential,total"
    cols = read_energy_csv(tmp_path / "energy.csv")
    arr = log.as_array()
    for i, name in enumerate(["t", "kinetic", "potential", "total"]):
        np.testing.assert_array_equal(cols[name], arr[:, i])  # bit-exact (repr)
    np.testing.assert_array_equal(cols["total"][:-1], rows[:, 0] + rows[:, 1])
    assert cols["total"][-1] == 3.5

    for src in (tmp_path / "energy.csv", str(tmp_path / "energy.csv"), log, cols, arr):
        png = tmp_path / "energy.png"
        plot_energy(src, png)
        with Image.open(png) as im:
            assert im.format == "PNG" and im.size == (700, 400)
            a = np.asarray(im.convert("RGB"))
            assert (a < 200).any()  # something drawn
    assert _listing(tmp_path) == ["energy.csv", "energy.png"]


def test_energy_csv_bad_file(tmp_path):
    p = tmp_path / "e.csv"
    p.write_text("a,b\n1,2\n")
    with pytest.raises(InputError):
        read_energy_csv(p)
    p.write_text("t,kinetic,potential,total\n1,2,3,4\n1,2,x,4\n")
    with pytest.raises(InputError) as exc:
        read_energy_csv(p)
    assert exc.value.line == 3


# ----------------------------------------------------------------------------- preview


def _deforming_torus(n_frames: int, nu: int = 24, nv: int = 12):
    V, F = torus(nu, nv)
    frames = []
    for k in range(n_frames):
        s = 0.8 * k / max(n_frames - 1, 1)
        W = V.copy()
        W[:, 1] += s * W[:, 0] ** 2  # bend upward, monotonically
        frames.append(W)
    return frames, F


def test_render_preview_gif(tmp_path):
    frames, F = _deforming_torus(12)
    gif = tmp_path / "preview.gif"
    png = tmp_path / "first.png"
    render_preview(frames, F, gif, fps=10, size=160, first_frame_png=png)
    with Image.open(gif) as im:
        assert im.format == "GIF"
        assert im.n_frames == 12
        assert im.size == (160, 160)
        arrays = [np.asarray(fr.convert("RGB")).astype(int) for fr in ImageSequence.Iterator(im)]
    assert max(np.abs(a - arrays[0]).max() for a in arrays[1:]) > 0
    assert np.abs(arrays[-1] - arrays[0]).mean() > 0.5  # really moves
    with Image.open(png) as im:
        a = np.asarray(im.convert("RGB")).astype(int)
    mesh_px = (a.sum(axis=2) < 3 * 250).mean()
    assert 0.05 < mesh_px < 0.9  # an object, not blank, not filled
    grey = a[a.sum(axis=2) < 3 * 250].sum(axis=1)
    assert grey.max() - grey.min() > 60  # shaded, not flat
    assert sorted(p.name for p in tmp_path.iterdir()) == ["first.png", "preview.gif"]


def test_render_preview_subsamples_and_decimates(tmp_path):
    frames, F = _deforming_torus(100, nu=60, nv=30)  # 3600 faces
    gif = tmp_path / "p.gif"
    render_preview(frames, F, gif, size=96, max_frames=20, max_faces=800)
    with Image.open(gif) as im:
        assert im.n_frames == 20


def test_cluster_decimate_keeps_closed_surface():
    V, F = torus(80, 40)
    A, Fc = _cluster_decimate(V, F, 1000)
    assert 0 < Fc.shape[0] <= 1000
    np.testing.assert_allclose(np.asarray(A.sum(axis=1)).ravel(), 1.0)
    assert Fc.max() < A.shape[0]
    # closed: every edge shared by an even number of faces
    e = np.sort(np.concatenate([Fc[:, [0, 1]], Fc[:, [1, 2]], Fc[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert np.all(counts % 2 == 0)


def test_render_preview_refuses_non_finite(tmp_path):
    frames, F = _deforming_torus(3)
    frames[1] = frames[1].copy()
    frames[1][0, 0] = np.nan
    with pytest.raises(SimulationError):
        render_preview(frames, F, tmp_path / "x.gif")
    assert _listing(tmp_path) == []


# ----------------------------------------------------------------------------- checkpoints


def test_checkpoint_bit_exact_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    q = rng.normal(size=(259, 3))
    q[0, 0] = -0.0
    q[0, 1] = 5e-324  # subnormal
    q[0, 2] = np.nan
    v = rng.normal(size=(259, 3)) * 1e-300
    T = rng.integers(0, 259, (627, 4))
    path = tmp_path / "state.ckpt"  # no .npz suffix added
    save_checkpoint(path, q=q, v=v, T=T, t=0.37, step=np.int64(37), scene="arma", params={"E": 6e5})
    assert _listing(tmp_path) == ["state.ckpt"]
    out = load_checkpoint(path)
    assert set(out) == {"q", "v", "T", "t", "step", "scene", "params"}
    for name, a in (("q", q), ("v", v), ("T", T)):
        assert out[name].dtype == a.dtype and out[name].shape == a.shape
        assert out[name].tobytes() == a.tobytes()
    assert out["t"] == 0.37 and out["step"] == 37 and out["scene"] == "arma"
    assert out["params"] == {"E": 6e5}


def test_checkpoint_errors(tmp_path):
    with pytest.raises(ValueError):
        save_checkpoint(tmp_path / "a.npz", x=np.array([object()], dtype=object))
    with pytest.raises(ValueError):
        save_checkpoint(tmp_path / "a.npz", x={1, 2})  # a set is not JSON
    assert _listing(tmp_path) == []
    with pytest.raises(InputError):
        load_checkpoint(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError):
        load_checkpoint(tmp_path / "junk.npz")
    np.savez(tmp_path / "plain.npz", a=np.zeros(3))
    with pytest.raises(InputError):
        load_checkpoint(tmp_path / "plain.npz")


def test_render_preview_view_bounds_all_keeps_every_frame_inside(tmp_path):
    frames, F = _deforming_torus(6)
    for bounds, clipped in (("first", True), ("all", False)):
        gif = tmp_path / f"{bounds}.gif"
        render_preview(frames, F, gif, size=120, view_bounds=bounds, margin=0.02)
        with Image.open(gif) as im:
            im.seek(im.n_frames - 1)
            a = np.asarray(im.convert("RGB")).astype(int)
        top_row_has_mesh = (a[0].sum(axis=1) < 3 * 250).any()
        assert top_row_has_mesh == clipped
    with pytest.raises(ValueError):
        render_preview(frames, F, tmp_path / "x.gif", view_bounds="middle")


@pytest.mark.parametrize("elev", [90.0, -90.0, 0.0])
def test_render_preview_any_elevation(tmp_path, elev):
    frames, F = _deforming_torus(2)
    png = tmp_path / "f.png"
    render_preview(frames, F, tmp_path / "a.gif", size=64, elev=elev, first_frame_png=png)
    with Image.open(png) as im:
        assert (np.asarray(im.convert("L")) < 250).any()


def test_run_writes_strain_gravity_and_pull_energies(tmp_path):
    """energy.csv splits V into strain and gravity (and logs the pull springs): a dropped
    bunny's V goes negative by gravity alone, its strain stays >= 0."""
    from fem3d.app.cli import main

    out = tmp_path / "drop"
    assert main(["run", "contact_bunny_drop", "--steps", "30", "--out", str(out), "--quiet",
                 "--frame-every", "30"]) == 0
    text = (out / "energy.csv").read_text()
    assert text.splitlines()[0] == "t,kinetic,potential,total,strain,gravity,pull"
    c = read_energy_csv(out / "energy.csv")
    np.testing.assert_allclose(c["strain"] + c["gravity"], c["potential"], rtol=1e-12,
                               atol=1e-12 * np.abs(c["potential"]).max())
    assert c["gravity"][-1] < 0.0 and c["potential"][-1] < 0.0
    assert (c["strain"] >= -1e-9 * np.abs(c["gravity"]).max()).all()
    assert c["strain"].max() > 0.0  # it landed (step 25) and squashed
    assert (c["pull"] == 0.0).all()
    assert (out / "energy.png").stat().st_size > 0


def test_resume_of_a_run_written_before_the_energy_split(tmp_path):
    """A checkpoint and energy.csv of the old 4-column layout resume; the inherited rows keep
    their values (split unknown: nan), the new rows carry the split."""
    from fem3d.app.cli import main
    from fem3d.io.checkpoint import CHECKPOINT_NAME, load_run_checkpoint, save_run_checkpoint

    out = tmp_path / "old"
    assert main(["run", "contact_incline", "--steps", "4", "--checkpoint-every", "4", "--out",
                 str(out), "--quiet", "--no-preview"]) == 0
    ck = load_run_checkpoint(out / CHECKPOINT_NAME)
    assert ck.energy.shape == (5, 7)
    old = ck.energy[:, :4].copy()
    ck.energy = old
    save_run_checkpoint(out / CHECKPOINT_NAME, ck)  # as a run before the split wrote it
    (out / "energy.csv").write_text(EnergyLog.from_array(old).to_csv())
    assert (out / "energy.csv").read_text().startswith("t,kinetic,potential,total\n")
    assert load_run_checkpoint(out / CHECKPOINT_NAME).energy.shape == (5, 4)
    assert main(["resume", str(out), "--steps", "8", "--quiet"]) == 0
    c = read_energy_csv(out / "energy.csv")
    assert len(c["t"]) == 9
    for i, name in enumerate(["t", "kinetic", "potential", "total"]):
        np.testing.assert_array_equal(c[name][:5], old[:, i])  # inherited rows, exact
    assert np.isnan(c["strain"][:5]).all() and np.isfinite(c["strain"][5:]).all()
    np.testing.assert_allclose(c["strain"][5:] + c["gravity"][5:], c["potential"][5:],
                               rtol=1e-12, atol=1e-15)
    assert load_run_checkpoint(out / CHECKPOINT_NAME).energy.shape[1] == 7 or not (
        out / CHECKPOINT_NAME).exists()

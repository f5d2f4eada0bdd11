"""Robustness, round 2 (issue 12): each class of fault has its test, through what the user
sees (the CLI's exit status, its one-line message, the files left behind).

* non-regular inputs (FIFO, device) are refused by every reader, never read (a FIFO would
  block forever: the readers run in a subprocess with a timeout);
* symlink loops are reported as such;
* outputs that would overwrite the run's inputs are refused;
* the output folder is locked for a run's lifetime; a stale lock (kill -9) is taken over;
* runs and resumes remove the ``.<name>.tmp*`` files a killed writer left;
* disk full names the file being written, and the last checkpoint stays loadable;
* a ``--skin`` far outside the simulation mesh is refused;
* parser failures say what is wrong with the file, not which Python exception fired;
* warnings are one prefixed line each, and the error is the last line.
"""

from __future__ import annotations

import errno
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.errors import InputError
from fem3d.io import rundir
from fem3d.io.checkpoint import CHECKPOINT_NAME, load_run_checkpoint
from fem3d.mesh.formats import read_surface_mesh, read_tet_mesh, write_tet_mesh
from fem3d.mesh.tetmesh import TetMesh

ROOT = Path(__file__).resolve().parents[2]
ARMA = str(ROOT / "data" / "arma_6.node")  # 259 vertices, no skin: cheap frames
BUNNY = str(ROOT / "data" / "coarser_bunny.mesh")
#: A Python exception class name quoted in a message ("IndexError", "KeyError: 'x'", ...).
PY_INTERNALS = re.compile(r"\b[A-Z][A-Za-z]*(Error|Exception)\b|Traceback|list index")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["OMP_NUM_THREADS"] = "1"
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "fem3d", *args], capture_output=True,
                          text=True, env=_env(), timeout=timeout, cwd=ROOT)


def _here(capsys: pytest.CaptureFixture[str], *args: str) -> subprocess.CompletedProcess[str]:
    """``fem3d ARGS`` in this process (what ``python -m fem3d`` runs: ``sys.exit(main())``),
    its exit status and stderr: the same message as :func:`_cli` without a ~1 s interpreter
    start. Not for what depends on the process (warnings' display, a blocking read)."""
    capsys.readouterr()
    rc = main(list(args))
    return subprocess.CompletedProcess(["fem3d", *args], rc, "", capsys.readouterr().err)


def _one_line_error(stderr: str) -> str:
    """The stderr of a refused command: its last line is the error; return it."""
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert lines, "nothing on stderr"
    assert "Traceback" not in stderr, stderr
    assert "error:" in lines[-1], stderr
    return lines[-1]


# ---------------------------------------------------------------- non-regular input files

READERS = """
import sys
from fem3d.mesh.formats import read_surface_mesh, read_tet_mesh
from fem3d.io.checkpoint import load_checkpoint
from fem3d.errors import InputError
for name, fn in (("mesh", read_tet_mesh), ("msh", read_tet_mesh), ("vtu", read_tet_mesh),
                 ("node", read_tet_mesh), ("obj", read_surface_mesh), ("npz", load_checkpoint),
                 ("dev", read_tet_mesh)):
    path = sys.argv[1] + "." + name if name != "dev" else "/dev/zero"
    try:
        fn(path)
        print(name, "ACCEPTED")
    except InputError as exc:
        print(name, "REFUSED", str(exc))
"""


def test_every_reader_refuses_fifos_and_devices(tmp_path: Path) -> None:
    base = tmp_path / "pipe"
    for ext in ("mesh", "msh", "vtu", "node", "ele", "obj", "npz"):
        os.mkfifo(f"{base}.{ext}")
    r = subprocess.run([sys.executable, "-c", READERS, str(base)], capture_output=True,
                       text=True, env=_env(), timeout=60)  # a reader that opens one hangs
    assert r.returncode == 0, r.stderr
    lines = dict(ln.split(" ", 1) for ln in r.stdout.splitlines())
    assert len(lines) == 7, r.stdout
    for name, result in lines.items():
        assert result.startswith("REFUSED"), (name, result)
        kind = "a device" if name == "dev" else "a named pipe (FIFO)"
        assert f"is {kind}, not a regular" in result, result
        assert "\n" not in result


def test_cli_refuses_a_fifo_mesh(tmp_path: Path) -> None:
    fifo = tmp_path / "in.mesh"
    os.mkfifo(fifo)
    r = _cli("run", str(fifo), "--steps", "1", "--out", str(tmp_path / "o"), timeout=60)
    assert r.returncode == 2
    assert "named pipe (FIFO)" in _one_line_error(r.stderr) and str(fifo) in r.stderr


def test_symlink_loop_is_named(tmp_path: Path) -> None:
    a, b = tmp_path / "a.mesh", tmp_path / "b.mesh"
    a.symlink_to(b)
    b.symlink_to(a)
    with pytest.raises(InputError, match="symbolic link loop"):
        read_tet_mesh(a)
    with pytest.raises(InputError, match="symbolic link loop"):
        read_surface_mesh(b)
    (tmp_path / "dangling.obj").symlink_to(tmp_path / "gone.obj")
    with pytest.raises(InputError, match="broken symbolic link"):
        read_surface_mesh(tmp_path / "dangling.obj")


# ---------------------------------------------------------------- parser messages


def test_parser_failures_describe_the_file(tmp_path: Path) -> None:
    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    T = np.array([[0, 1, 2, 3]])
    for ext in ("vtu", "msh", "vtk"):
        write_tet_mesh(tmp_path / f"full.{ext}", TetMesh(X, T))
        data = (tmp_path / f"full.{ext}").read_bytes()
        for cut in (len(data) // 3, len(data) // 2, len(data) - 20):
            p = tmp_path / f"cut{cut}.{ext}"
            p.write_bytes(data[:cut])
            try:
                got = read_tet_mesh(p)
            except InputError as exc:
                msg = str(exc)
                assert str(p) in msg and "\n" not in msg
                assert not PY_INTERNALS.search(msg), msg
            else:  # a cut that still loads must have lost nothing (no silent partial mesh)
                np.testing.assert_array_equal(got.X, X, err_msg=f"{p.name}: vertices")
                np.testing.assert_array_equal(got.T, T, err_msg=f"{p.name}: tets")
    p = tmp_path / "png.vtu"
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(InputError, match="not a readable VTU file") as info:
        read_tet_mesh(p)
    assert not PY_INTERNALS.search(str(info.value))


def test_bad_checkpoints_are_described_not_quoted(tmp_path: Path, capsys) -> None:
    out = tmp_path / "run"
    assert main(["run", ARMA, "--steps", "3", "--checkpoint-every", "3", "--out", str(out),
                 "--no-preview", "--quiet"]) == 0
    ck = out / CHECKPOINT_NAME
    data = ck.read_bytes()
    for bad, what in ((data[: len(data) // 2], "truncated"), (b"hello\n", "text"),
                      (b"", "empty")):
        ck.write_bytes(bad)
        r = _here(capsys, "resume", str(out), "--steps", "5")
        assert r.returncode == 2, (what, r.stderr)
        line = _one_line_error(r.stderr)
        assert str(ck) in line and "checkpoint" in line, line
        assert not PY_INTERNALS.search(line) and "zip file" not in line, (what, line)


# ---------------------------------------------------------------- outputs over inputs


def test_run_refuses_to_overwrite_its_input_mesh(tmp_path: Path, capsys) -> None:
    out = tmp_path / "DIR"
    assert main(["run", ARMA, "--steps", "2", "--out", str(out), "--no-preview", "--quiet"]) == 0
    frame = out / "frames" / "frame_00000.vtu"  # a triangle frame: refused before reading
    tets = out / "frames" / "frame_00001.vtu"  # a frame that is a valid tet mesh
    write_tet_mesh(tets, read_tet_mesh(ARMA))
    for victim in (frame, tets):
        before = victim.read_bytes()
        r = _here(capsys, "run", str(victim), "--steps", "1", "--out", str(out),
                  "--no-preview", "--quiet")
        assert r.returncode == 2, r.stderr
        line = _one_line_error(r.stderr)
        assert "overwrite its own mesh" in line and str(victim) in line, line
        assert victim.read_bytes() == before  # untouched


@pytest.mark.parametrize("role", ["mesh", "skin", "scene file", "checkpoint"])
def test_overwrite_check_covers_every_input(tmp_path: Path, role: str) -> None:
    out = tmp_path / "o"
    (out / "frames").mkdir(parents=True)
    for victim in (out / "frames" / "frame_00003.obj", out / "energy.csv",
                   out / "checkpoint.npz", out / "frames.pvd"):
        victim.write_text("x")
        with pytest.raises(InputError, match=f"overwrite its own {role}"):
            rundir.check_overwrite(out, {role: victim})
    rundir.check_overwrite(out, {role: tmp_path / "elsewhere.mesh"})  # fine
    ck = out / "checkpoint.npz"  # a resume replaces its own checkpoint, on purpose
    rundir.check_overwrite(out, {role: ck}, allow=(ck,))


# ---------------------------------------------------------------- the folder lock


def _start_run(out: Path, steps: int = 100000) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "fem3d", "run", ARMA, "--steps", str(steps), "--out", str(out),
         "--no-preview", "--quiet", "--checkpoint-every", "5"],
        env=_env(), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )


def _wait(pred, timeout: float, what: str):  # noqa: ANN001, ANN202
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(0.1)
    pytest.fail(f"timed out waiting for {what}")


def test_output_folder_is_locked_and_stale_locks_are_taken_over(tmp_path: Path,
                                                                capsys) -> None:
    # the first run is a process of its own (killed -9 below); the others run here
    out = tmp_path / "run"
    first = _start_run(out)
    try:
        _wait(lambda: (out / CHECKPOINT_NAME).exists(), 90, "the first run to checkpoint")
        r = _here(capsys, "run", ARMA, "--steps", "3", "--out", str(out), "--no-preview",
                  "--quiet")
        assert r.returncode == 2, r.stderr
        line = _one_line_error(r.stderr)
        assert f"in use by process {first.pid}" in line and "fem3d" in line, line
        r = _here(capsys, "resume", str(out), "--steps", "1000000")  # resume refuses too
        assert r.returncode == 2 and f"process {first.pid}" in _one_line_error(r.stderr)
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=30)
    # kill -9 mid-run: the lock file stays, a frame temp file is left behind.
    assert (out / rundir.LOCK_NAME).exists()
    junk = [out / "frames" / ".frame_00007.tmpab12cd.vtu", out / ".energy.tmpzz.csv"]
    for j in junk:
        j.write_text("partial")
    target = load_run_checkpoint(out / CHECKPOINT_NAME).step + 3
    r = _here(capsys, "resume", str(out), "--steps", str(target))
    assert r.returncode == 0, r.stderr
    assert not any(j.exists() for j in junk), "resume left the killed run's temp files"
    assert load_run_checkpoint(out / CHECKPOINT_NAME).step == target
    junk[0].write_text("partial")
    r = _here(capsys, "run", ARMA, "--steps", "2", "--out", str(out), "--no-preview",
              "--quiet")
    assert r.returncode == 0, r.stderr
    assert not junk[0].exists(), "run left a temp file behind"


def test_lock_is_released_after_a_run(tmp_path: Path) -> None:
    out = tmp_path / "o"
    with rundir.claim(out):
        with pytest.raises(InputError, match=f"in use by process {os.getpid()}"), \
                rundir.claim(out):
            pass  # a second claim from the same process is refused too (flock per open)
    with rundir.claim(out):
        pass


# ---------------------------------------------------------------- disk full


def test_disk_full_names_the_file_and_keeps_the_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from fem3d.io.files import atomic_write
    from fem3d.io.frames import NumberedFilesWriter

    out = tmp_path / "full"
    real = NumberedFilesWriter.write
    calls = {"n": 0}

    def write(self, step_index, t, V, point_data=None):  # noqa: ANN001, ANN202
        calls["n"] += 1
        if calls["n"] < 8:
            return real(self, step_index, t, V, point_data)
        target = self.path_of(step_index)

        def fill(p: Path) -> None:
            p.write_bytes(b"partial")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        atomic_write(target, fill)
        raise AssertionError("unreachable")

    monkeypatch.setattr(NumberedFilesWriter, "write", write)
    code = main(["run", ARMA, "--steps", "20", "--checkpoint-every", "3", "--out", str(out),
                 "--no-preview", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    line = _one_line_error(err)
    assert "No space left on device" in line and "frame_00007.vtu" in line, line
    ck = load_run_checkpoint(out / CHECKPOINT_NAME)  # still loadable
    assert ck.step == 6
    assert not [p for p in out.rglob(".*tmp*")], "the failed write left its temp file"


# ---------------------------------------------------------------- skins far away


def test_skin_far_outside_is_refused(tmp_path: Path) -> None:
    V, F = read_surface_mesh(ROOT / "data" / "bunny_skin.obj")
    far = tmp_path / "far.obj"
    with open(far, "w") as fh:
        for v in V + np.array([1000.0, 0.0, 0.0]):
            fh.write(f"v {v[0]} {v[1]} {v[2]}\n")
        for f in F + 1:
            fh.write(f"f {f[0]} {f[1]} {f[2]}\n")
    r = _cli("run", BUNNY, "--skin", str(far), "--steps", "1", "--out", str(tmp_path / "o"),
             "--no-preview", "--quiet")
    assert r.returncode == 2, r.stderr
    line = _one_line_error(r.stderr)
    assert "far outside the simulation mesh" in line and str(far) in line


def test_warnings_are_one_prefixed_line_and_the_error_is_last(tmp_path: Path) -> None:
    V, F = read_surface_mesh(ROOT / "data" / "bunny_skin.obj")
    h = float(np.ptp(V[:, 1]))
    near = tmp_path / "near.obj"  # sticks out by ~0.1 diagonal: a warning, not an error
    with open(near, "w") as fh:
        for v in V + np.array([0.25 * h, 0.0, 0.0]):
            fh.write(f"v {v[0]} {v[1]} {v[2]}\n")
        for f in F + 1:
            fh.write(f"f {f[0]} {f[1]} {f[2]}\n")
    r = _cli("run", BUNNY, "--skin", str(near), "--steps", "1", "--out", str(tmp_path / "o"),
             "--no-preview", "--quiet",
             "--set", "bodies[0].pins=[{select={box=[[1e9,1e9,1e9],[2e9,2e9,2e9]]}}]")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    warn = [ln for ln in lines if "warning:" in ln]
    assert warn and all(ln.startswith("fem3d run: warning: ") for ln in warn), r.stderr
    assert not any("warnings.warn" in ln for ln in lines), r.stderr
    assert r.returncode == 2, r.stderr
    assert lines[-1].startswith("fem3d run: error: "), r.stderr


def _fail_writes_of(monkeypatch: pytest.MonkeyPatch, module, name: str, after: int) -> None:
    """Make ``module.atomic_write`` run out of space on ``name`` after ``after`` good writes
    (a partial temp file is written first, so its clean-up is checked too)."""
    real = module.atomic_write
    seen = {"n": 0}

    def atomic_write(target, content, *args, **kwargs):  # noqa: ANN001, ANN202
        if Path(target).name != name:
            return real(target, content, *args, **kwargs)
        seen["n"] += 1
        if seen["n"] <= after:
            return real(target, content, *args, **kwargs)

        def fill(p: Path) -> None:
            p.write_bytes(b"partial")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        return real(target, fill)

    monkeypatch.setattr(module, "atomic_write", atomic_write)


@pytest.mark.parametrize("which", ["checkpoint", "energy"])
def test_disk_full_on_the_checkpoint_and_the_energy_log(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
    which: str,
) -> None:
    import fem3d.io.checkpoint as checkpoint
    import fem3d.io.energy as energy

    module, name = {"checkpoint": (checkpoint, CHECKPOINT_NAME),
                    "energy": (energy, "energy.csv")}[which]
    _fail_writes_of(monkeypatch, module, name, after=1)
    out = tmp_path / "full"
    code = main(["run", ARMA, "--steps", "12", "--checkpoint-every", "3", "--out", str(out),
                 "--no-preview", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    line = _one_line_error(err)
    assert "No space left on device" in line and name in line, line
    assert not [p for p in out.rglob(".*tmp*")], "the failed write left its temp file"
    if which == "checkpoint":  # the first checkpoint survives the failed second one
        assert load_run_checkpoint(out / CHECKPOINT_NAME).step == 3


def test_disk_full_on_the_sweep_results(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import fem3d.app.sweep.results as results

    _fail_writes_of(monkeypatch, results, "results.csv", after=0)
    spec = tmp_path / "s.toml"  # every case rejected by the scene: no cluster is started
    spec.write_text(f'scene = "{ARMA}"\n[grid]\n"bodies[0].material.nu" = [0.7, 0.8]\n',
                    encoding="utf-8")
    code = main(["sweep", str(spec), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    line = _one_line_error(err)
    assert "No space left on device" in line and "results.csv" in line, line
    assert not [p for p in (tmp_path / "out").rglob(".*tmp*")]

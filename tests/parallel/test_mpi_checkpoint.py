"""Checkpoints of distributed runs: ``mpiexec -n 2 fem3d run --checkpoint-every`` writes the
one-process ``checkpoint.npz``; ``fem3d resume`` continues it on 2 ranks bit for bit, and on
1 rank, as a 2-rank resume continues a one-process run's, to Newton's tolerance."""

from __future__ import annotations

import re
import signal
import time

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.io.checkpoint import CHECKPOINT_NAME, load_run_checkpoint
from fem3d.scene import load_scene
from fem3d.simulation import Simulation
from tests.parallel.helpers import (
    MESH,
    relative_difference,
    run_mpi,
    start_mpi,
    write_scene,
)

# mpiexec's ranks poll while they wait: with another test on the cores they crawl
pytestmark = pytest.mark.alone

#: CG + GAMG: the default KSP of a distributed system above 1e4 free DOFs, and bit for bit
#: the same from run to run on 2 ranks (MUMPS on 2 ranks is not: its dynamic scheduling
#: sums in another order from run to run, docs/parallel.md)
GAMG = ['--set', 'simulation.linear_solver=petsc',
        '--set', 'simulation.petsc_options="-ksp_type cg -pc_type gamg"']


def _ok(proc) -> None:
    assert proc.returncode == 0, proc.stderr[-3000:]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The one-process run of the bdf2 box, 20 steps (the default direct solver)."""
    folder = tmp_path_factory.mktemp("reference")
    sim = Simulation(load_scene(str(write_scene(folder, integrator="bdf2"))))
    for _ in range(20):
        sim.step()
    return sim


def test_resume_on_two_ranks_is_bit_exact(tmp_path):
    """20 steps on 2 ranks equal, bit for bit, 10 steps on 2 ranks then a 2-rank resume to
    20: the state (BDF2's history too), energy.csv, every frame's pieces."""
    scene = str(write_scene(tmp_path, integrator="bdf2"))
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    _ok(run_mpi(2, "run", scene, "--steps", "20", "--checkpoint-every", "20", "--out",
                str(straight), *GAMG, cwd=tmp_path))
    _ok(run_mpi(2, "run", scene, "--steps", "10", "--checkpoint-every", "10", "--out",
                str(resumed), *GAMG, cwd=tmp_path))
    half = load_run_checkpoint(resumed / CHECKPOINT_NAME)
    assert half.step == 10 and half.settings["ranks"] == 2
    assert half.partition.shape == (3072,) and set(half.partition.tolist()) == {0, 1}
    assert sorted(half.frames) == list(range(11))
    _ok(run_mpi(2, "resume", str(resumed), "--steps", "20", cwd=tmp_path))
    a = load_run_checkpoint(straight / CHECKPOINT_NAME)
    b = load_run_checkpoint(resumed / CHECKPOINT_NAME)
    assert b.step == 20
    for key in ("q", "v", "history_q_prev", "history_v_prev"):
        assert np.array_equal(a.snapshot[key], b.snapshot[key]), key
    assert np.array_equal(a.energy, b.energy) and a.frames == b.frames
    for name in ("energy.csv", "frames.pvd", "frames/frame_00020_0.vtu",
                 "frames/frame_00020_1.vtu", "frames/frame_00015.pvtu"):
        assert (straight / name).read_bytes() == (resumed / name).read_bytes(), name


def test_resume_of_one_process_on_two_ranks(tmp_path, reference):
    """A one-process run's checkpoint at step 10, continued on 2 ranks to 20: the
    one-process run to 1e-8 of the motion; its frames list the one-process .vtu frames then
    the 2-rank .pvtu."""
    scene = str(write_scene(tmp_path, integrator="bdf2"))
    out = tmp_path / "out"
    assert main(["run", scene, "--steps", "10", "--checkpoint-every", "10", "--out", str(out),
                 "--quiet", "--no-preview"]) == 0
    _ok(run_mpi(2, "resume", str(out), "--steps", "20", cwd=tmp_path))
    ckpt = load_run_checkpoint(out / CHECKPOINT_NAME)
    assert ckpt.step == 20 and ckpt.settings["ranks"] == 2
    diff = relative_difference(ckpt.snapshot["q"], reference.q, reference.model.X)
    print(f"1 rank -> 2 ranks: relative difference {diff:.2e}")
    assert diff <= 1e-8
    assert relative_difference(ckpt.snapshot["v"], reference.v, 0.0 * reference.v) <= 1e-6
    files = [ckpt.frames[s][1] for s in sorted(ckpt.frames)]
    assert files[10] == "frames/frame_00010.vtu" and files[11] == "frames/frame_00011.pvtu"
    assert all((out / f).is_file() for f in files)
    assert ckpt.energy.shape == (21, 7)


def test_resume_of_two_ranks_in_one_process(tmp_path, reference):
    """A 2-rank run's checkpoint at step 10, continued by ``fem3d resume`` in one process
    (PETSc, the solver the run used): the one-process run to 1e-8 of the motion."""
    scene = str(write_scene(tmp_path, integrator="bdf2"))
    out = tmp_path / "out"
    _ok(run_mpi(2, "run", scene, "--steps", "10", "--checkpoint-every", "10", "--out",
                str(out), cwd=tmp_path))
    assert main(["resume", str(out), "--steps", "20", "--quiet"]) == 0
    ckpt = load_run_checkpoint(out / CHECKPOINT_NAME)
    assert ckpt.step == 20 and ckpt.settings["solver"] == "petsc"
    diff = relative_difference(ckpt.snapshot["q"], reference.q, reference.model.X)
    print(f"2 ranks -> 1 rank: relative difference {diff:.2e}")
    assert diff <= 1e-8
    files = [ckpt.frames[s][1] for s in sorted(ckpt.frames)]
    assert files[10] == "frames/frame_00010.pvtu" and files[11] == "frames/frame_00011.vtu"


def test_resume_on_two_ranks_refuses_a_changed_mesh(tmp_path):
    """A checkpoint whose mesh file changed since: one line naming it, exit 2."""
    scene = write_scene(tmp_path, integrator="implicit", steps=2)
    mesh = tmp_path / "bar.mesh"
    mesh.write_text(MESH.read_text())
    scene.write_text(scene.read_text().replace(str(MESH), str(mesh)))
    out = tmp_path / "out"
    _ok(run_mpi(2, "run", str(scene), "--checkpoint-every", "2", "--out", str(out),
                cwd=tmp_path))
    mesh.write_text(MESH.read_text().replace("\n0.0625 0 0 0\n", "\n0.0626 0 0 0\n", 1))
    proc = run_mpi(2, "resume", str(out), "--steps", "4", cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "mesh differs" in lines[0], proc.stderr



def _interrupt(tmp_path, signum: int, env: dict[str, str] | None = None
               ) -> tuple[int, list[str], int]:
    """A 400-step 2-rank run of the bdf2 box (CG + GAMG) sent ``signum`` (to mpiexec) once
    its fourth frame is written; its exit status, stderr's lines and the step its message
    names."""
    scene = str(write_scene(tmp_path, integrator="bdf2", steps=400))
    out = tmp_path / "out"
    proc = start_mpi(2, "run", scene, "--out", str(out), *GAMG, cwd=tmp_path, env=env)
    try:
        deadline = time.monotonic() + 300  # a stall guard only (a loaded machine)
        while not (out / "frames" / "frame_00004.pvtu").exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.2)
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    # Open MPI's launcher may add libevent's "[warn] Epoll ..." while it tears the ranks
    # down (a race inside mpiexec, not fem3d's output): only fem3d's lines are asserted on.
    lines = [line for line in err.strip().splitlines() if not line.startswith("[warn] ")]
    ours = [line for line in lines if line.startswith("fem3d ")]
    found = re.search(r"interrupted by SIG\w+ at step (\d+) ", ours[-1] if ours else "")
    assert len(ours) == 1 and found, err
    return proc.returncode, lines, int(found.group(1))


def test_sigusr1_on_two_ranks_checkpoints_and_resumes_bit_exact(tmp_path):
    """SIGUSR1 to ``mpiexec`` (Open MPI forwards it to every rank): the ranks finish the
    step, agree on it, save its checkpoint and exit 130 with the one-process line;
    ``mpiexec -n 2 fem3d resume`` continues it bit for bit the uninterrupted run."""
    status, lines, step = _interrupt(tmp_path, signal.SIGUSR1)
    out = tmp_path / "out"
    assert status == 130 and len(lines) == 1, lines
    assert lines[0] == (f"fem3d run: interrupted by SIGUSR1 at step {step} (t = "
                        f"{0.01 * step:.4g}); checkpoint {out / CHECKPOINT_NAME}; continue "
                        f"with: fem3d resume {out}")
    ckpt = load_run_checkpoint(out / CHECKPOINT_NAME)
    assert 4 <= ckpt.step == step < 400 and len(ckpt.energy) == step + 1
    end = str(step + 3)
    _ok(run_mpi(2, "resume", str(out), "--steps", end, cwd=tmp_path))
    straight = tmp_path / "straight"
    _ok(run_mpi(2, "run", str(tmp_path / "box.toml"), "--steps", end, "--out",
                str(straight), *GAMG, cwd=tmp_path))
    a, b = np.load(straight / "state.npz"), np.load(out / "state.npz")
    assert int(b["step"]) == step + 3
    assert np.array_equal(a["q"], b["q"]) and np.array_equal(a["v"], b["v"])
    assert (straight / "energy.csv").read_bytes() == (out / "energy.csv").read_bytes()


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_to_mpiexec_checkpoints_within_its_grace(tmp_path, signum):
    """SIGTERM or SIGINT to Open MPI's ``mpiexec``: it sends the ranks SIGTERM and, after
    ``odls_base_sigkill_timeout`` s (2 here, 10 times a step of the box; 1 by default),
    SIGKILL; the ranks save the checkpoint of the step they finish before that and print
    the one-process line (mpiexec's own exit status is its abort's, not 130). mpiexec waits
    the timeout out twice: the test takes about 5 s (alone on the cores: ``alone``)."""
    status, lines, step = _interrupt(tmp_path, signum,
                                     {"OMPI_MCA_odls_base_sigkill_timeout": "2"})
    ours = [line for line in lines if line.startswith("fem3d ")]
    assert status != 0 and ours[0].startswith("fem3d run: interrupted by SIGTERM"), lines
    ckpt = load_run_checkpoint(tmp_path / "out" / CHECKPOINT_NAME)
    assert 4 <= ckpt.step == step < 400
    assert np.load(tmp_path / "out" / "state.npz")["step"] == step

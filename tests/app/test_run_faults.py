"""Faults during a run: checkpoints and bit-exact resume, SIGINT/SIGTERM, inverted elements in
backward Euler's line search, non-finite states, and parameter errors through the CLI.

The bit-exact check by hand (any scene; ``cmp`` prints nothing when the files are equal)::

    fem3d run arma --steps 40 --checkpoint-every 40 --out /tmp/A --no-preview
    fem3d run arma --steps 13 --checkpoint-every 13 --out /tmp/B --no-preview
    fem3d resume /tmp/B --steps 40
    cmp /tmp/A/energy.csv /tmp/B/energy.csv && cmp /tmp/A/frames.pvd /tmp/B/frames.pvd
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import fem3d.solve.schemes.implicit as backward_euler
import fem3d.solve.schemes.linear as linearly_implicit
from fem3d.app.cli import main
from fem3d.errors import InputError, SimulationError
from fem3d.io.checkpoint import CHECKPOINT_NAME, load_run_checkpoint
from fem3d.io.energy import read_energy_csv
from fem3d.physics.assembly import count_inverted
from fem3d.scene import apply_overrides, load_scene, scene_from_arrays
from fem3d.simulation import Simulation
from fem3d.solve.integrators import State, implicit_euler, linearly_implicit_euler
from fem3d.solve.state import new_state

ROOT = Path(__file__).resolve().parents[2]
ARMA = str(ROOT / "data" / "arma_6.node")  # 259 vertices, no skin: cheap frames
BUNNY = str(ROOT / "data" / "coarser_bunny.mesh")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["OMP_NUM_THREADS"] = "1"
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _leftovers(out: Path) -> list[str]:
    """Temporary or hidden files anywhere under ``out`` (atomic writes leave none; the lock
    file ``.fem3d.lock`` is removed when a run ends, see fem3d.io.rundir)."""
    return [str(p) for p in out.rglob("*") if p.name.startswith(".") or ".tmp" in p.name]


def _assert_no_nan_in_outputs(out: Path) -> None:
    import meshio

    for p in out.rglob("*"):
        if p.suffix in (".csv", ".pvd"):
            text = p.read_text().lower()
            assert "nan" not in text and "inf" not in text, p
        elif p.suffix == ".vtu":
            assert np.isfinite(meshio.read(p).points).all(), p
    csv = read_energy_csv(out / "energy.csv")
    assert all(np.isfinite(c).all() for c in csv.values())
    if (out / CHECKPOINT_NAME).exists():
        load_run_checkpoint(out / CHECKPOINT_NAME)  # refuses non-finite values


def _compare_runs(a: Path, b: Path) -> None:
    """Uninterrupted run ``a`` and checkpointed + resumed run ``b`` are bit for bit equal."""
    ca, cb = load_run_checkpoint(a / CHECKPOINT_NAME), load_run_checkpoint(b / CHECKPOINT_NAME)
    assert ca.step == cb.step
    for key in ("q", "v", "pull_vertices", "pull_targets", "script_active"):
        assert np.array_equal(ca.snapshot[key], cb.snapshot[key]), key
    for key in ("t", "injected", "pull_k"):
        assert ca.snapshot[key] == cb.snapshot[key], key
    ea, eb = read_energy_csv(a / "energy.csv"), read_energy_csv(b / "energy.csv")
    for col in ea:
        assert np.array_equal(ea[col], eb[col]), col
    assert (a / "energy.csv").read_bytes() == (b / "energy.csv").read_bytes()
    assert np.array_equal(ca.energy, cb.energy)
    assert (a / "frames.pvd").read_text() == (b / "frames.pvd").read_text()
    fa = sorted(p.name for p in (a / "frames").iterdir())
    assert fa == sorted(p.name for p in (b / "frames").iterdir())
    for name in fa:
        assert (a / "frames" / name).read_bytes() == (b / "frames" / name).read_bytes(), name


# ------------------------------------------------------------------------------------------
# checkpoint + resume == uninterrupted, bit for bit


@pytest.mark.parametrize(
    "argv, n, k, solver",
    [
        # backward Euler; the split falls while the scripted pull is attached (t < 0.3)
        ([ARMA], 36, 12, None),
        # linearly-implicit (runaway-energy bookkeeping), SuperLU (orders on first use)
        ([BUNNY, "--integrator", "linear"], 24, 9, "superlu"),
        # NumPy kernels, PSD Newton Hessian, split after the release
        ([ARMA, "--kernels", "numpy", "--hessian", "psd", "--newton-iterations", "3"], 34, 31,
         None),
        # factorizations reused across steps: the checkpoint rebuilds the same preconditioner
        ([ARMA, "--newton-solver", "reuse"], 30, 11, None),
    ],
    ids=["arma-implicit", "bunny-linear-superlu", "arma-numpy-psd", "arma-reuse"],
)
def test_resume_is_bit_exact(tmp_path, capsys, monkeypatch, argv, n, k, solver):
    if solver:
        monkeypatch.setenv("FEM3D_SOLVER", solver)
    common = ["--quiet", "--no-preview", "--frame-every", "4"]
    a, b = tmp_path / "straight", tmp_path / "resumed"
    assert main(["run", *argv, "--steps", str(n), "--checkpoint-every", str(n),
                 "--out", str(a), *common]) == 0
    assert main(["run", *argv, "--steps", str(k), "--checkpoint-every", str(k),
                 "--out", str(b), *common]) == 0
    assert load_run_checkpoint(b / CHECKPOINT_NAME).step == k
    assert main(["resume", str(b), "--steps", str(n), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert f"steps {k} -> {n}" in err
    _compare_runs(a, b)
    assert not _leftovers(a) and not _leftovers(b)


def test_superlu_needs_no_first_factorization_state():
    """A fresh solver (a resumed run) computes what a long-lived one does (SuperLU primed)."""
    scene = load_scene(BUNNY, {"simulation.integrator": "linear",
                               "simulation.linear_solver": "superlu"})
    a = Simulation(scene, scripted=True)
    b = Simulation(scene, scripted=True)
    for _ in range(6):
        a.step()
    for _ in range(3):
        b.step()
    c = Simulation(scene, scripted=True)
    c.restore(b.snapshot())
    for _ in range(3):
        c.step()
    assert np.array_equal(a.q, c.q) and np.array_equal(a.v, c.v) and a.t == c.t


def test_resume_errors(tmp_path, capsys):
    assert main(["resume", str(tmp_path / "nothing"), "--quiet"]) == 2
    assert "no checkpoint" in capsys.readouterr().err
    out = tmp_path / "r"
    assert main(["run", ARMA, "--steps", "4", "--checkpoint-every", "2", "--out", str(out),
                 "--quiet", "--no-preview"]) == 0
    capsys.readouterr()
    assert main(["resume", str(out), "--steps", "2", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "below the checkpoint's step 4" in err and len(err.splitlines()) == 1
    (out / CHECKPOINT_NAME).write_bytes(b"PK\x03\x04 truncated")
    assert main(["resume", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "checkpoint" in err and "Traceback" not in err


# ------------------------------------------------------------------------------------------
# SIGINT / SIGTERM mid-run


def _wait_for(predicate, timeout: float, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if proc.poll() is not None:
            raise AssertionError(f"fem3d run ended early: {proc.communicate()}")
        if time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"timed out: {proc.communicate()}")
        time.sleep(0.02)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_saves_checkpoint_and_resume_completes(tmp_path, capsys, signum):
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "fem3d", "run", ARMA, "--steps", "100000", "--frame-every", "3",
         "--checkpoint-every", "5", "--out", str(out), "--quiet", "--no-preview"],
        cwd=ROOT, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        # a stall guard only: a loaded machine starts the armadillo slowly
        _wait_for(lambda: (out / CHECKPOINT_NAME).exists(), 600, proc)
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    name = signal.Signals(signum).name
    last = err.strip().splitlines()[-1]
    assert f"interrupted by {name}" in last and "fem3d resume" in last
    assert "Traceback" not in err
    ckpt = load_run_checkpoint(out / CHECKPOINT_NAME)
    s = ckpt.step
    assert s >= 5
    rows = read_energy_csv(out / "energy.csv")
    assert len(rows["t"]) == s + 1 and np.array_equal(rows["total"], ckpt.energy[:, 3])
    frames = sorted((out / "frames").glob("*.vtu"))
    assert [int(f.stem[-5:]) for f in frames] == list(range(0, s + 1, 3))
    assert (out / "frames.pvd").read_text().count("<DataSet") == len(frames)
    assert not _leftovers(out)
    _assert_no_nan_in_outputs(out)

    # resume to completion, then compare with an uninterrupted run of the same length
    target = s + 4
    assert main(["resume", str(out), "--steps", str(target), "--quiet"]) == 0
    straight = tmp_path / "straight"
    assert main(["run", ARMA, "--steps", str(target), "--frame-every", "3", "--checkpoint-every",
                 "5", "--out", str(straight), "--quiet", "--no-preview"]) == 0
    capsys.readouterr()
    _compare_runs(straight, out)
    assert not _leftovers(out)


# ------------------------------------------------------------------------------------------
# backward Euler's line search never accepts inverted elements


def _one_tet_sim() -> Simulation:
    X = np.array([[0, 0, 0], [0, 0, 1.0], [1, 0, 0], [0, 1, 0]])  # apex 3 at y = 1
    T = np.array([[0, 1, 2, 3]])
    scene = scene_from_arrays(X, T, {
        "bodies[0].material": {"E": 1e5, "nu": 0.4, "density": 1000.0},
        "bodies[0].pins": [{"select": {"lowest_y": {"tol": 1e-9}}}],
        "interaction": {"spring_k": 1e4, "pick_radius": 0.01}}, name="tet")
    sim = Simulation(scene)
    assert sim.fixed_vertices.tolist() == [0, 1, 2]
    return sim


def _falling_apex(sim: Simulation, speed: float, step: int = 7) -> State:
    v = np.zeros((4, 3))
    v[3, 1] = -speed  # straight through the base: q + dt v inverts the tet
    return State(q=sim.model.X.copy(), v=v, t=0.07, step=step)


@pytest.mark.parametrize("speed", [300.0, 1e4, 1e6])
def test_line_search_backtracks_past_inverting_trials(speed):
    sim = _one_tet_sim()
    state = _falling_apex(sim, speed)
    assert count_inverted(sim.model, state.q + sim.dt * state.v) == 1  # v_t inverts
    new, stats = implicit_euler(sim.system, state, sim.dt)
    assert stats.line_search_halvings > 0
    assert count_inverted(sim.model, new.q) == 0 and 0 < new.q[3, 1] < 1
    assert np.isfinite(new.q).all() and np.isfinite(new.v).all()


def test_no_admissible_step_raises_with_count_and_step():
    sim = _one_tet_sim()
    with pytest.raises(SimulationError, match=r"inverts 1 of 1 tets") as info:
        implicit_euler(sim.system, _falling_apex(sim, 1e14, step=7), sim.dt)
    assert info.value.step == 7 and str(info.value).startswith("step 7:")
    # through Simulation.step: the error is raised and the state stays at the last good step
    sim.set_state(sim.model.X, _falling_apex(sim, 1e14).v, t=0.5, step=50)
    q0, v0 = sim.q.copy(), sim.v.copy()
    with pytest.raises(SimulationError, match="no acceptable Newton step") as info:
        sim.step()
    assert info.value.step == 50
    assert np.array_equal(sim.q, q0) and np.array_equal(sim.v, v0)
    assert (sim.t, sim.step_index) == (0.5, 50)


def test_flat_tet_is_inadmissible():
    sim = _one_tet_sim()
    q = sim.model.X.copy()
    q[3, 1] = 0.0  # det F = 0 exactly
    with pytest.raises(SimulationError, match="inadmissible"):
        implicit_euler(sim.system, State(q=q, v=np.zeros_like(q), step=3), sim.dt)


# ------------------------------------------------------------------------------------------
# non-finite states


def _patch_new_state(monkeypatch, corrupted) -> None:
    """``new_state`` replaced where both integrators call it."""
    for module in (backward_euler, linearly_implicit):
        monkeypatch.setattr(module, "new_state", corrupted)


def _nan_after(step: int):
    real = new_state

    def corrupted(system, state, v_free, dt, *rest):
        new = real(system, state, v_free, dt, *rest)
        if state.step >= step:
            q = new.q.copy()
            q[5, 1] = math.nan
            return State(q=q, v=new.v, t=new.t, step=new.step)
        return new

    return corrupted


@pytest.mark.parametrize("integrator", [linearly_implicit_euler, implicit_euler])
def test_integrators_check_for_non_finite_state(monkeypatch, integrator):
    sim = Simulation(load_scene(ARMA))
    _patch_new_state(monkeypatch, _nan_after(0))
    state = State.at_rest(sim.model)
    state = State(q=state.q, v=state.v, step=4)
    with pytest.raises(SimulationError, match="non-finite") as info:
        integrator(sim.system, state, sim.dt)
    assert info.value.step == 4


@pytest.mark.parametrize("integrator", ["linear", "implicit"])
def test_cli_stops_on_non_finite_state_without_writing_nan(tmp_path, capsys, monkeypatch,
                                                           integrator):
    _patch_new_state(monkeypatch, _nan_after(6))
    out = tmp_path / "nan"
    status = main(["run", ARMA, "--integrator", integrator, "--steps", "20", "--frame-every",
                   "2", "--checkpoint-every", "4", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert status == 1, err
    assert "simulation failed" in err and "step 6" in err and "non-finite" in err
    assert "last good step (6" in err
    rows = read_energy_csv(out / "energy.csv")
    assert len(rows["t"]) == 7  # steps 0..6
    assert sorted(int(f.stem[-5:]) for f in (out / "frames").glob("*.vtu")) == [0, 2, 4, 6]
    assert (out / "energy.png").exists() and (out / "preview.gif").exists()
    assert load_run_checkpoint(out / CHECKPOINT_NAME).step == 4
    _assert_no_nan_in_outputs(out)
    assert not _leftovers(out)


# ------------------------------------------------------------------------------------------
# parameters: a clear error, one stderr line, exit status 2 (the --dt -1 and --steps -3 cases
# are in tests/app/test_cli_run.py)


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--rho", "0"], "bodies[0].material.density"),
        (["--rho", "-0.1"], "bodies[0].material.density"),
        (["--E", "0"], "bodies[0].material.E"),
        (["--E=-6e5"], "bodies[0].material.E"),
        (["--E", "nan"], "bodies[0].material.E"),
        (["--nu", "0.5"], "bodies[0].material.nu"),
        (["--nu", "-1"], "bodies[0].material.nu"),
        (["--nu", "0.7"], "bodies[0].material.nu"),
        (["--dt", "0"], "--dt"),
        (["--dt", "inf"], "--dt"),
        (["--steps", "-1"], "--steps"),
        (["--set", "bodies[0].pins[0].select={box=[[0,-100,0],[1,-99,1]]}"],
         "bodies[0].pins[0].select.box: selects no vertex"),
        (["--set", "pulls[0].select={sphere={center=[0,0,5],radius=0.001}}"],
         "pulls[0].select.sphere: selects no vertex"),
        (["--pick-radius", "-1"], "pick_radius"),
        (["--checkpoint-every", "-2"], "--checkpoint-every"),
        (["--frame-every", "0"], "--frame-every"),
    ],
)
def test_cli_bad_parameter_exits_2_with_one_line(tmp_path, capsys, extra, needle):
    status = main(["run", ARMA, "--steps", "2", *extra, "--out", str(tmp_path / "x"),
                   "--quiet", "--no-preview"])
    err = capsys.readouterr().err.strip()
    assert status == 2, err
    assert needle in err
    assert len(err.splitlines()) == 1 and "Traceback" not in err


def test_cli_debug_shows_traceback(tmp_path, capsys):
    status = main(["--debug", "run", ARMA, "--rho", "0", "--out", str(tmp_path), "--quiet"])
    err = capsys.readouterr().err
    assert status == 2 and "Traceback" in err and "material.density" in err


def test_api_parameter_errors():
    scene = load_scene(ARMA)
    with pytest.raises(InputError, match="no pinned vertex"):
        Simulation(apply_overrides(scene, {"bodies[0].pins": []}))
    far = apply_overrides(scene, {"pulls[0].select": {"sphere": {"center": [0.0, 0.0, 9.0],
                                                                 "radius": 1e-6}}})
    with pytest.raises(InputError, match=r"pulls\[0\]\.select\.sphere: selects no vertex"):
        Simulation(far, scripted=True)
    for bad in ({"bodies[0].material.density": 0.0}, {"bodies[0].material.E": -1.0},
                {"bodies[0].material.nu": 0.5}, {"bodies[0].material.nu": -1.0},
                {"simulation.dt": 0.0}):
        with pytest.raises(InputError, match=next(iter(bad)).replace("[", r"\[")):
            load_scene(ARMA, bad)
    with pytest.raises(InputError):
        Simulation(scene).restore({**Simulation(scene).snapshot(), "q": np.zeros((3, 3))})


def test_newton_refuses_a_non_finite_gradient_and_survives_a_huge_one():
    from fem3d.solve.newton import newtons_method

    def energy(x):
        return float(x @ x)

    with pytest.raises(SimulationError, match="gradient is not finite"):
        newtons_method(np.ones(2), energy, lambda x: np.array([math.inf, 0.0]),
                       lambda x, g: -g)
    # finite components whose plain 2-norm overflows: still a proper (finite) norm
    res = newtons_method(np.full(2, 1e300), lambda x: 1.0, lambda x: x, lambda x, g: -g,
                         max_iterations=0)
    assert res.gradient_norms[0] == pytest.approx(math.sqrt(2) * 1e300)


@pytest.mark.parametrize("n_signals, saved_step", [(1, 6), (2, 5)],
                         ids=["finish-step", "abandon-step"])
def test_in_process_signal_finishes_or_abandons_the_step(tmp_path, capsys, monkeypatch,
                                                          n_signals, saved_step):
    """One SIGINT during step 6 lets it finish; a second one abandons it (state of step 5)."""
    real_step = Simulation.step
    # what the run must put back (a shell's background job starts with SIGINT ignored)
    handler_before = signal.getsignal(signal.SIGINT)

    def step(self):
        if self.step_index == 5:
            for _ in range(n_signals):
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.01)  # let the handler run
        return real_step(self)

    monkeypatch.setattr(Simulation, "step", step)
    out = tmp_path / "int"
    status = main(["run", ARMA, "--steps", "50", "--frame-every", "2", "--out", str(out),
                   "--quiet", "--no-preview"])
    err = capsys.readouterr().err
    assert status == 130, err
    assert f"interrupted by SIGINT at step {saved_step}" in err
    ckpt = load_run_checkpoint(out / CHECKPOINT_NAME)
    assert ckpt.step == saved_step
    assert len(read_energy_csv(out / "energy.csv")["t"]) == saved_step + 1
    assert max(ckpt.frames) == saved_step - saved_step % 2
    assert not _leftovers(out)
    assert signal.getsignal(signal.SIGINT) is handler_before  # handlers restored

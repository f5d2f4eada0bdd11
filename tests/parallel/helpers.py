"""What the PETSc and MPI tests share: a two-material box scene and how to launch
``mpiexec`` here (tests/solve/test_petsc_solver.py, tests/parallel/test_mpi_run.py)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

#: several command lines in one launch of ranks (:func:`run_mpi_batch`)
BATCH_SCRIPT = Path(__file__).with_name("batch_runs.py")
MESH = Path(__file__).resolve().parents[2] / "data" / "scenes" / "meshes" / "bar_16x4x4.mesh"


def box_scene_text(integrator: str = "implicit", *, steps: int = 20,
                   linear_solver: str = "auto", extra: str = "") -> str:
    """Two 1 x 0.25 x 0.25 bars (1,536 tets each) clamped at x = 0, sagging under gravity
    and set moving: Neo-Hookean, and StVK with Rayleigh damping."""
    return f"""
[simulation]
integrator = "{integrator}"
dt = 0.01
steps = {steps}
gravity = [0.0, -9.81, 0.0]
linear_solver = "{linear_solver}"
{extra}

[[bodies]]
mesh = "{MESH}"
velocity = [0.0, 0.0, 0.3]
material = {{ model = "neo_hookean", E = 2e5, nu = 0.35, density = 1000.0 }}
pins = [{{ select = {{ box = [[-1.0, -1.0, -1.0], [1e-6, 1.0, 1.0]] }} }}]

[[bodies]]
mesh = "{MESH}"
transform = {{ translate = [0.0, 0.0, 0.5] }}
material = {{ model = "stvk", E = 5e5, nu = 0.3, density = 800.0 }}
damping = {{ rayleigh_stiffness = 0.002, rayleigh_mass = 0.5 }}
pins = [{{ select = {{ box = [[-1.0, -1.0, -1.0], [1e-6, 1.0, 1.0]] }} }}]
"""


def write_scene(folder: Path, **kwargs) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "box.toml"
    path.write_text(box_scene_text(**kwargs))
    return path


def relative_difference(q: np.ndarray, reference: np.ndarray, rest: np.ndarray) -> float:
    """``|q - reference| / |reference - rest|``: the difference relative to the motion."""
    return float(np.linalg.norm(q - reference) / np.linalg.norm(reference - rest))


def mpiexec_or_skip() -> list[str]:
    """The ``mpiexec -n`` prefix of this machine (Open MPI as root allowed); skips when MPI
    or petsc4py cannot run here, fails instead under ``FEM3D_REQUIRE_MPI=1`` (CI)."""
    reason = None
    exe = shutil.which("mpiexec")
    if exe is None:
        reason = "no mpiexec (bash scripts/install_petsc.sh installs Open MPI and PETSc)"
    else:
        try:
            import mpi4py  # noqa: F401
            import petsc4py  # noqa: F401
        except ImportError as exc:
            reason = f"{exc} (pip install 'fem3d[mpi]' after scripts/install_petsc.sh)"
    if reason is not None:
        if os.environ.get("FEM3D_REQUIRE_MPI") == "1":
            pytest.fail(f"FEM3D_REQUIRE_MPI=1 but MPI cannot run here: {reason}")
        pytest.skip(reason)
    version = subprocess.run([exe, "--version"], capture_output=True, text=True).stdout
    openmpi = "Open MPI" in version or "OpenRTE" in version
    # Open MPI's --quiet: without it, a rank's non-zero exit adds mpiexec's own banner
    return [exe, *(["--oversubscribe", "--quiet"] if openmpi else []), "-n"]


def mpi_env() -> dict[str, str]:
    """The environment of an ``mpiexec`` run: one thread per rank, Open MPI allowed as
    root."""
    return {**os.environ, "OMP_NUM_THREADS": "1", "OMPI_ALLOW_RUN_AS_ROOT": "1",
            "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1", "OMPI_MCA_rmaps_base_oversubscribe": "1",
            # a rank waiting for the other gives its core up (machines shared by other work)
            "OMPI_MCA_mpi_yield_when_idle": "1"}


def run_mpi(ranks: int, *args: str, cwd: Path, timeout: float = 120.0
            ) -> subprocess.CompletedProcess:
    """``mpiexec -n ranks python -m fem3d args...``."""
    cmd = [*mpiexec_or_skip(), str(ranks), sys.executable, "-m", "fem3d", *args]
    return subprocess.run(cmd, cwd=cwd, env=mpi_env(), capture_output=True, text=True,
                          timeout=timeout)


def start_mpi(ranks: int, *args: str, cwd: Path, env: dict[str, str] | None = None
              ) -> subprocess.Popen:
    """``mpiexec -n ranks python -m fem3d args...`` started, not waited for (``env`` added
    to :func:`mpi_env`)."""
    cmd = [*mpiexec_or_skip(), str(ranks), sys.executable, "-m", "fem3d", *args]
    return subprocess.Popen(cmd, cwd=cwd, env={**mpi_env(), **(env or {})},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def run_mpi_batch(ranks: int, runs: dict[str, list[str]], cwd: Path, timeout: float = 300.0
                  ) -> dict[str, subprocess.CompletedProcess]:
    """Each of ``runs``' ``fem3d`` command lines, one after another on the same ``ranks``
    ranks: one launch for runs whose outputs the tests then read (tests/parallel/batch_runs.py
    says why). Per run, its exit status and (rank 0's) stderr, as :func:`run_mpi` gives
    them; a launch that fails as a whole gives every run its status and stderr."""
    plan = cwd / "batch.json"
    plan.write_text(json.dumps(runs))
    cmd = [*mpiexec_or_skip(), str(ranks), sys.executable, str(BATCH_SCRIPT), str(plan)]
    proc = subprocess.run(cmd, cwd=cwd, env=mpi_env(), capture_output=True, text=True,
                          timeout=timeout)
    results = plan.with_suffix(".results.json")
    if proc.returncode != 0 or not results.exists():
        return {name: subprocess.CompletedProcess(cmd, proc.returncode or 1, proc.stdout,
                                                  proc.stderr) for name in runs}
    return {name: subprocess.CompletedProcess(runs[name], int(r["status"]), "", r["stderr"])
            for name, r in json.loads(results.read_text()).items()}


def two_rank_runs(tmp_path_factory: pytest.TempPathFactory, name: str,
                  scenes: dict[str, Callable[[Path], Path]]
                  ) -> dict[str, tuple[Path, subprocess.CompletedProcess]]:
    """``fem3d run`` of each of ``scenes`` (a name -> a function writing the scene into a
    folder) on 2 ranks, in one launch (:func:`run_mpi_batch`) that has the cores alone:
    name -> (the run's scene, beside its ``out``; the run's exit status and stderr)."""
    from tests.conftest import cores

    root = tmp_path_factory.mktemp(name)
    runs = {}
    for k, (case, make) in enumerate(scenes.items()):
        folder = root / f"case{k}"
        folder.mkdir()
        runs[case] = ["run", str(make(folder)), "--out", str(folder / "out")]
    with cores(tmp_path_factory, alone=True):
        procs = run_mpi_batch(2, runs, cwd=root)
    return {case: (Path(runs[case][1]), procs[case]) for case in runs}

"""Run the trajectory cases and (re-)record their CPU-neutral reference.

The cases are the gallery scenes, the classic bunny and armadillo and the Newton / linear-solver
variants (``reuse``, the PSD Hessian, AMG, the NumPy kernels) as first recorded at commit 6cbcdd9
before the restructuring of issue 19. ``tests/data/trajectory_reference.npz`` holds float64
states, never digests (bits are a property of one machine; docs/testing.md):

* smooth cases: q and v at :func:`checkpoint_steps`; the last row is the final state of the
  6cbcdd9 recording (``--historical``), the earlier rows were recorded by the current code;
* contact cases: each body's centre of mass and bounding box at the last step.

``tests/simulation/test_trajectories.py`` compares against it within per-case tolerances,
``tests/simulation/test_determinism.py`` compares runs made during the test bit for bit. Run
``python tests/record_trajectories.py`` only to re-record on purpose (a deliberate change of
behaviour), never to make a failing test pass; ``--deviations`` prints each case's largest
deviation from the reference (the table of docs/testing.md).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(__file__).resolve().parent / "data"
REFERENCE = DATA / "trajectory_reference.npz"

#: fTetWild's output for the surface scenes, fixed: fTetWild gives a different mesh from run to
#: run of the same input (four runs of coarser_bunny.obj: 480, 477, 477 and 471 vertices), so
#: these scenes read theirs through a cache seeded from ``<scene>.body<i>.mesh`` here.
FIXED_TETWILD = DATA / "tetwild"

#: contact_bunny_drop as it was when recorded: the scene has since gained self-contact and
#: stiffness damping (issue 21: it intersected itself at landing and did not come to rest)
BUNNY_DROP_AS_RECORDED = {"contact.self_contact": False,
                          "bodies[0].damping.rayleigh_stiffness": 0.0,
                          "contact.newton_start": "clamped", "contact.max_substeps": 1,
                          "contact.first_step": "confirm"}
#: contact scenes as recorded: Newton started from the CCD-clamped velocity and no substeps
#: (the spec's defaults; the gallery's drop, stack and fold set newton_start = "q_t", and
#: all but the pile contact.max_substeps = 8, since issue 21's rounds; the stack the reuse
#: Newton solver since stop 28 and CHOLMOD simplicial in stops 28-31, supernodal since;
#: every contact scene contact.first_step = "accept" since stop 34)
CONTACT_AS_RECORDED = {"contact.newton_start": "clamped", "contact.max_substeps": 1,
                       "simulation.newton.solver": "direct", "simulation.cholmod": "auto",
                       "contact.first_step": "confirm"}

#: the PSD projection as recorded: cyclic Jacobi (QL replaced it at stop 31; the cases that
#: project an indefinite dP/dF, Newton's "psd" Hessian and stiffness damping, keep Jacobi)
JACOBI = {"simulation.psd_projection": "jacobi"}

# (case name, scene name, steps, --set overrides; "_backend" picks the kernel back end)
CASES: list[tuple[str, str, int, dict]] = [
    ("bunny", "bunny", 100, {}),
    ("arma", "arma", 100, {}),
    ("arma_reuse", "arma", 100, {"simulation.newton.solver": "reuse"}),
    ("arma_psd", "arma", 40, {"simulation.newton.hessian": "psd", **JACOBI}),
    ("arma_numpy", "arma", 60, {"_backend": "numpy"}),
    ("bunny_implicit", "bunny", 40, {"simulation.integrator": "implicit"}),
    ("cantilever", "cantilever", 40, JACOBI),
    ("cantilever_amg", "cantilever", 20, {"simulation.linear_solver": "amg", **JACOBI}),
    ("twist", "twist", 40, {}),
    ("swing", "swing", 40, {}),
    ("two_pulls", "two_pulls", 120, {}),
    ("jelly_pair", "jelly_pair", 40, {}),
    ("jelly_stvk", "jelly_stvk", 30, {}),
    ("jelly_neo_hookean", "jelly_neo_hookean", 30, {}),
    ("bunny_surface", "bunny_surface", 20, {}),
    ("armadillo_surface", "armadillo_surface", 20, JACOBI),
    ("contact_bunny_drop", "contact_bunny_drop", 80, BUNNY_DROP_AS_RECORDED),
    ("contact_bunny_drop_reuse", "contact_bunny_drop", 80,
     {**BUNNY_DROP_AS_RECORDED, "simulation.newton.solver": "reuse"}),
    ("contact_incline", "contact_incline", 80, CONTACT_AS_RECORDED),
    ("contact_stack", "contact_stack", 120, CONTACT_AS_RECORDED),
    ("contact_twisted_bar", "contact_twisted_bar", 300, CONTACT_AS_RECORDED),
]
CASE = {c[0]: c for c in CASES}
#: checked by their physics and a final pose band (tests/simulation/test_trajectories.py)
CONTACT_CASES = tuple(c[0] for c in CASES if c[0].startswith("contact_"))
SMOOTH_CASES = tuple(c[0] for c in CASES if c[0] not in CONTACT_CASES)


def digest(a: np.ndarray) -> str:
    """SHA-256 of ``a`` as contiguous float64 (for comparisons within one machine only)."""
    return hashlib.sha256(np.ascontiguousarray(a, dtype=np.float64).tobytes()).hexdigest()


def checkpoint_steps(steps: int) -> tuple[int, ...]:
    """The 1-based steps whose q, v a smooth case's reference keeps: the first (where the pulls
    and gravity act first), a quarter, half way and the last."""
    return tuple(sorted({1, max(1, steps // 4), max(1, steps // 2), steps}))


@contextmanager
def fixed_tetwild_meshes(scene_name: str, scene):
    """``$FEM3D_CACHE`` at a folder holding this scene's fixed fTetWild meshes (if it has any)."""
    from fem3d.mesh.tetrahedralize import cache_key

    fixed = {i: FIXED_TETWILD / f"{scene_name}.body{i}.mesh" for i in range(len(scene.bodies))}
    fixed = {i: f for i, f in fixed.items() if f.is_file()}
    if not fixed:
        yield
        return
    before = os.environ.get("FEM3D_CACHE")
    with tempfile.TemporaryDirectory() as cache:
        (Path(cache) / "tetwild").mkdir()
        for i, mesh in fixed.items():
            body = scene.bodies[i]
            opts = body.tetrahedralize
            key = cache_key(scene.path(body.mesh), opts.edge_length, opts.epsilon,
                            opts.stop_quality)
            shutil.copyfile(mesh, Path(cache) / "tetwild" / f"{key[:40]}.mesh")
        os.environ["FEM3D_CACHE"] = cache
        try:
            yield
        finally:
            if before is None:
                os.environ.pop("FEM3D_CACHE", None)
            else:
                os.environ["FEM3D_CACHE"] = before


@dataclass(frozen=True)
class Trajectory:
    """One run of a case: every step's state and what the physics checks need.

    Attributes
    ----------
    digests : list of str
        SHA-256 of q and v after each step (comparisons within one process or machine).
    q, v : (steps + 1, n_vertices, 3) float64
        The states, the initial one first.
    energy : (steps + 1,) float64
        Kinetic + strain + gravity energy of each state (without the contact barrier).
    mass : (n_vertices,) float64
        Row sums of the consistent mass matrix (momentum = ``mass @ v``, exactly).
    body : (n_vertices,) int
        The connected component (body) of each vertex.
    faces : (n_faces, 3) int
        The boundary triangles of all bodies.
    planes : list of (point, normal)
        The plane obstacles.
    gravity : (3,) float64
    dt : float
    scene : fem3d.scene.Scene
        The scene as run (contact settings, pins).
    """

    digests: list[str]
    q: np.ndarray
    v: np.ndarray
    energy: np.ndarray
    mass: np.ndarray
    body: np.ndarray
    faces: np.ndarray
    planes: list
    gravity: np.ndarray
    dt: float
    scene: Any


def _bodies(T: np.ndarray, n: int) -> np.ndarray:
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    rows = np.repeat(T[:, 0], T.shape[1])
    graph = sp.coo_matrix((np.ones(T.size), (rows, T.ravel())), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def run_case(scene_name: str, steps: int, overrides: dict) -> Trajectory:
    """Step one case (a scene, a step count, ``--set`` overrides) and keep every state."""
    from fem3d.scene import apply_overrides, load_scene
    from fem3d.simulation import Simulation

    overrides = dict(overrides)
    backend = overrides.pop("_backend", None)
    scene = apply_overrides(load_scene(scene_name), overrides)
    with fixed_tetwild_meshes(scene_name, scene):
        sim = Simulation(scene, scripted=True, backend=backend)
    q, v, energy, digests = [sim.q.copy()], [sim.v.copy()], [sim.energies()["total"]], []
    for _ in range(steps):
        sim.step()
        digests.append(digest(sim.q) + digest(sim.v))
        q.append(sim.q.copy())
        v.append(sim.v.copy())
        energy.append(sim.energies()["total"])
    n = sim.q.shape[0]
    mass = np.asarray(sim.model.mass.sum(axis=1)).reshape(n, 3)[:, 0]
    planes = [(np.array(o.plane.point), np.array(o.plane.normal)) for o in scene.obstacles
              if o.plane is not None]
    return Trajectory(digests, np.array(q), np.array(v), np.array(energy), mass,
                      _bodies(sim.model.T, n), sim.surface_faces, planes,
                      np.array(scene.simulation.gravity, dtype=float), scene.simulation.dt,
                      scene)


@functools.cache
def trajectory(name: str) -> Trajectory:
    """The one run of case ``name`` this process shares between the regression, physics and
    determinism tests."""
    _, scene_name, steps, overrides = CASE[name]
    return run_case(scene_name, steps, overrides)


def body_poses(q: np.ndarray, mass: np.ndarray, body: np.ndarray) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """Each body's centre of mass ``(n_bodies, 3)`` and bounding box ``(n_bodies, 2, 3)``."""
    ids = np.unique(body)
    com = np.array([np.average(q[body == b], axis=0, weights=mass[body == b]) for b in ids])
    box = np.array([[q[body == b].min(axis=0), q[body == b].max(axis=0)] for b in ids])
    return com, box


def reference_arrays(name: str, traj: Trajectory, historical=None) -> dict[str, np.ndarray]:
    """The reference entries of one case (with ``historical``, a smooth case's final q, v come
    from that recording)."""
    _, _, steps, _ = CASE[name]
    if name in CONTACT_CASES:
        com, box = body_poses(traj.q[-1], traj.mass, traj.body)
        return {f"{name}__com": com, f"{name}__box": box}
    at = np.array(checkpoint_steps(steps))
    q, v = traj.q[at].copy(), traj.v[at].copy()
    if historical is not None and f"{name}__q" in historical.files:
        q[-1], v[-1] = historical[f"{name}__q"], historical[f"{name}__v"]
    return {f"{name}__steps": at, f"{name}__q": q, f"{name}__v": v}


def deviation(name: str, traj: Trajectory, ref) -> tuple[float, float]:
    """The largest deviation from the reference: ``(|dq|, |dv|)`` over a smooth case's
    checkpoints, ``(|d com|, |d box|)`` of a contact case's final pose."""
    if name in CONTACT_CASES:
        com, box = body_poses(traj.q[-1], traj.mass, traj.body)
        return (float(np.abs(com - ref[f"{name}__com"]).max()),
                float(np.abs(box - ref[f"{name}__box"]).max()))
    at = ref[f"{name}__steps"]
    return (float(np.abs(traj.q[at] - ref[f"{name}__q"]).max()),
            float(np.abs(traj.v[at] - ref[f"{name}__v"]).max()))


#: runs ``fem3d`` command lines (JSON in argv[1]) one after another in one Python process;
#: energy.png is not drawn (matplotlib's import and plot, ~1 s a run, prove nothing here)
_CLI_LOOP = """import json, sys
import fem3d.io.preview
from fem3d.app.cli import main
fem3d.io.preview.plot_energy = lambda *args, **kwargs: None
for argv in json.loads(sys.argv[1]):
    if main(argv):
        sys.exit(f"fem3d {argv}: failed")
"""


def fem3d_in_a_new_process(commands: list[list[str]], cwd: Path) -> None:
    """Run several ``fem3d`` command lines (``["resume", DIR, ...]``) in one fresh process."""
    proc = subprocess.run([sys.executable, "-c", _CLI_LOOP, json.dumps(commands)], cwd=cwd,
                          capture_output=True, text=True, timeout=600)
    if proc.returncode:
        raise AssertionError(f"exit {proc.returncode}: {proc.stderr[-2000:]}")


def _with_e_scaled(name: str, rel: float) -> Trajectory:
    """Case ``name`` with every body's Young's modulus moved by ``rel`` relative (the mutation
    that the tolerances must catch)."""
    from fem3d.scene import load_scene

    _, scene_name, steps, overrides = CASE[name]
    bodies = load_scene(scene_name).bodies
    scaled = {f"bodies[{i}].material.E": b.material.E * (1.0 + rel) for i, b in enumerate(bodies)}
    return run_case(scene_name, steps, {**overrides, **scaled})


def print_deviations(e_rel: float | None = None) -> None:
    """Each case's largest deviation from the reference (``e_rel``: with E moved)."""
    ref = np.load(REFERENCE)
    for name, *_ in CASES:
        traj = trajectory(name) if e_rel is None else _with_e_scaled(name, e_rel)
        a, b = deviation(name, traj, ref)
        print(f"{name:26s} {a:.2e} {b:.2e}", flush=True)


def main(argv: list[str]) -> None:
    """``[--historical OLD.npz] [OUT]`` re-records; ``--deviations [E_REL]`` prints them."""
    if argv[:1] == ["--deviations"]:
        print_deviations(float(argv[1]) if len(argv) > 1 else None)
        return
    historical = None
    if argv[:1] == ["--historical"]:
        historical, argv = np.load(argv[1]), argv[2:]
    arrays: dict[str, np.ndarray] = {}
    for name, *_ in CASES:
        arrays |= reference_arrays(name, trajectory(name), historical)
        print(name, flush=True)
    np.savez_compressed(argv[0] if argv else REFERENCE, **arrays)


if __name__ == "__main__":
    main(sys.argv[1:])

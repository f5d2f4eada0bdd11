"""Record the trajectories of the gallery scenes and the Newton/linear-solver variants.

Written once before the restructuring of issue 19 (subpackages, objective terms, a small
integrator) so a test can prove the new code takes bit for bit the same steps:
``tests/data/trajectories_before_restructure.npz`` holds, per case, the SHA-256 of q and v
after every step and the final q, v. Run ``python tests/record_trajectories.py`` only to
re-record on purpose (a deliberate change of behaviour), never to make a failing test pass.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

#: fTetWild's output for the surface scenes, fixed: fTetWild gives a different mesh from run to
#: run of the same input (four runs of coarser_bunny.obj: 480, 477, 477 and 471 vertices), so
#: these scenes read theirs through a cache seeded from ``<scene>.body<i>.mesh`` here.
FIXED_TETWILD = Path(__file__).resolve().parent / "data" / "tetwild"

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


def digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a, dtype=np.float64).tobytes()).hexdigest()


@contextmanager
def fixed_tetwild_meshes(scene_name: str, scene):
    """``$FEM3D_CACHE`` at a folder holding this scene's fixed fTetWild meshes (if it has any)."""
    try:
        from fem3d.mesh.tetrahedralize import cache_key
    except ImportError:  # the code before the restructuring
        from fem3d.tetrahedralize import cache_key
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


def run_case(scene_name: str, steps: int, overrides: dict):
    """The q, v digests after each step and the final q, v of one case."""
    from fem3d.scene import apply_overrides, load_scene
    from fem3d.simulation import Simulation

    overrides = dict(overrides)
    backend = overrides.pop("_backend", None)
    scene = apply_overrides(load_scene(scene_name), overrides)
    with fixed_tetwild_meshes(scene_name, scene):
        sim = Simulation(scene, scripted=True, backend=backend)
    digests = []
    for _ in range(steps):
        sim.step()
        digests.append(digest(sim.q) + digest(sim.v))
    return digests, sim.q.copy(), sim.v.copy()


def main(out: str, only: list[str] | None = None) -> None:
    """Record every case into ``out``; with ``only``, re-record those cases and keep the rest."""
    arrays = dict(np.load(out)) if only else {}
    for name, scene_name, steps, overrides in CASES:
        if only and name not in only:
            continue
        digests, q, v = run_case(scene_name, steps, overrides)
        arrays[f"{name}__digests"] = np.array(digests)
        arrays[f"{name}__q"] = q
        arrays[f"{name}__v"] = v
        print(name, steps, digests[-1][:16], flush=True)
    np.savez_compressed(out, **arrays)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "tests/data/trajectories_before_restructure.npz",
         sys.argv[2:] or None)

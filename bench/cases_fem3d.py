"""fem3d's own benchmark rows: the reference of every ratio in docs/benchmarks.md.

=========================================================================================
FEM3D ROWS. Each block below is one function registering the rows of one fem3d layer;
they import fem3d lazily (inside ``setup``) and turn an ImportError into :class:`Skip`,
so the suite runs (peers only) while a layer is missing or not built.
To add a layer (a new integrator, a new kernel back end): write one ``_register_*``
function like these and call it at the bottom of this file.
=========================================================================================
"""

from __future__ import annotations

import numpy as np

from bench import BenchMesh, Skip, register


def _import_fem3d(what: str):
    """Import ``fem3d.<what>`` or raise Skip with the reason."""
    import importlib

    try:
        return importlib.import_module(f"fem3d.{what}")
    except Exception as err:  # noqa: BLE001 - ImportError, missing build, bad generated code
        raise Skip(f"fem3d.{what} not importable: {type(err).__name__}: {err}") from err


def _fem3d_model(mesh: BenchMesh, backend: str):
    """``fem3d.physics.model.build_model`` for the mesh with the kernel back end (Skip if
    absent)."""
    kernels = _import_fem3d("kernels.dispatch")
    try:
        kernels.material_kernels("neo_hookean", backend=backend)
    except Exception as err:  # noqa: BLE001 - e.g. the C extension is not built
        raise Skip(f"fem3d kernels backend {backend!r} unavailable: {err}") from err
    model_mod = _import_fem3d("physics.model")
    return model_mod.build_model(mesh.X, mesh.T, E=mesh.E, nu=mesh.nu, rho=mesh.rho,
                                 backend=backend)


# -------------------------------------------------------------------------------- kernels
def _register_kernel_rows(backend: str) -> None:
    """Energy, gradient, element Hessians and CSR Hessian with the generated kernels.

    The assembly is fem3d.physics.assembly's: ``np.bincount`` over the scatter maps precomputed in
    ``fem3d.physics.model.Model`` (fixed CSR pattern, no COO -> CSR per call).
    """
    lib = f"fem3d-{backend}"
    note = (f"{lib}: generated {backend} kernels (`fem3d.kernels.dispatch.material_kernels"
            f"(\"neo_hookean\", backend=\"{backend}\")`) + fem3d.physics.assembly (fixed pattern).")

    @register(f"energy/{lib}", group="energy", library=lib, note=note)
    def _energy(mesh: BenchMesh):
        model = _fem3d_model(mesh, backend)
        asm = _import_fem3d("physics.assembly")
        return lambda: asm.potential_energy(model, mesh.q)

    @register(f"gradient/{lib}", group="gradient", library=lib)
    def _gradient(mesh: BenchMesh):
        model = _fem3d_model(mesh, backend)
        asm = _import_fem3d("physics.assembly")
        return lambda: asm.assemble_gradient(model, mesh.q)

    @register(f"hessian_elements/{lib}", group="hessian_elements", library=lib)
    def _hess_e(mesh: BenchMesh):
        model = _fem3d_model(mesh, backend)
        asm = _import_fem3d("physics.assembly")
        # one output buffer reused across calls, as the Warp row reuses its (m, 12, 12) array
        out = np.empty((model.n_tets, 12, 12))

        def run():
            x_e = asm.element_positions(model, mesh.q)
            return model.mat.hessian(x_e, model.dphi_dX, model.vol, model.params, out=out)

        return run

    @register(f"hessian_csr/{lib}", group="hessian_csr", library=lib)
    def _hess_csr(mesh: BenchMesh):
        model = _fem3d_model(mesh, backend)
        asm = _import_fem3d("physics.assembly")
        return lambda: asm.assemble_hessian(model, mesh.q)


# -------------------------------------------------------------------------- linear solvers
_SOLVER_LIMITS = {"cholmod": 1.1e6, "pardiso": 1.1e6, "superlu": 1.1e5}
_SOLVER_REQUIRES = {"cholmod": ("sksparse",), "pardiso": ("pypardiso",), "superlu": ()}


def _register_solver_rows(backend: str) -> None:
    """fem3d.solve.linear.SparseSPDSolver: analysis, numeric factorization, solve."""
    lib = f"fem3d-linsolve-{backend}"
    kw = dict(library=lib, requires=_SOLVER_REQUIRES[backend], max_tets=_SOLVER_LIMITS[backend])
    notes = {
        "superlu": "fem3d-linsolve-superlu: SuperLU has no separate analysis; its first "
                   "factorization computes the ordering (the untimed warm-up call), later ones "
                   "reuse it.",
        "pardiso": "fem3d-linsolve-pardiso: MKL PARDISO, real SPD (mtype 2), METIS ordering, "
                   "phases 11 / 22 / 33 called directly (pypardiso's ctypes handle).",
        "cholmod": "fem3d-linsolve-cholmod: CHOLMOD via scikit-sparse, OpenBLAS; supernodal, "
                   "or simplicial LDL^T for small factors with short columns (`cholmod_mode`).",
    }

    def solver(mesh: BenchMesh):
        ls = _import_fem3d("solve.linear")
        if backend not in ls.available_linear_solvers(direct=True):
            raise Skip(f"fem3d.solve.linear back end {backend!r} not installed")
        A = mesh.system.A
        return analysed(ls, A), A

    def analysed(ls, A):
        s = ls.LINEAR_SOLVERS[backend]()
        s.analyse(A)
        return s

    @register(f"analyze/{lib}", group="analyze", note=notes[backend], **kw)
    def _analyze(mesh: BenchMesh):
        ls = _import_fem3d("solve.linear")
        _, A = solver(mesh)
        return lambda: analysed(ls, A)

    @register(f"factor/{lib}", group="factor", warmup_required=backend == "superlu", **kw)
    def _factor(mesh: BenchMesh):
        s, A = solver(mesh)
        return lambda: s.factorize(A)

    @register(f"solve/{lib}", group="solve", **kw)
    def _solve(mesh: BenchMesh):
        s, A = solver(mesh)
        s.factorize(A)
        b = np.ones(A.shape[0])
        return lambda: s.solve(b)


def _register_amg_rows() -> None:
    """fem3d.solve.linear.amg.AMGPreconditioner: aggregation ("analyze", once per pattern), numeric
    hierarchy setup ("factor") and preconditioned CG to a relative residual of 1e-8 from
    x = 0 ("solve"), on the same SPD system."""
    lib = "fem3d-amg"
    kw = dict(library=lib, requires=("pyamg",))
    note = ("fem3d-amg: pyamg smoothed aggregation (rigid-body modes as B, 3x3 BSR, "
            "fem3d.solve.linear.amg); analyze = aggregation (structure only), factor = numeric "
            "hierarchy setup, solve = V-cycle preconditioned CG to |r| <= 1e-8 |b|.")

    def amg(mesh: BenchMesh):
        ls = _import_fem3d("solve.linear.amg")
        free_vertices = mesh.system.free[::3] // 3
        return ls.AMGPreconditioner(ls.rigid_body_modes(mesh.X[free_vertices])), mesh.system.A

    @register(f"analyze/{lib}", group="analyze", note=note, **kw)
    def _analyze(mesh: BenchMesh):
        pre, A = amg(mesh)
        return lambda: pre.analyze(A)

    @register(f"factor/{lib}", group="factor", **kw)
    def _factor(mesh: BenchMesh):
        pre, A = amg(mesh)
        pre.analyze(A)
        return lambda: pre.setup(A)

    @register(f"solve/{lib}", group="solve", **kw)
    def _solve(mesh: BenchMesh):
        pre, A = amg(mesh)
        pre.setup(A)
        b = np.ones(A.shape[0])

        def run():
            result = pre.solve(A, b, rtol=1e-8, maxiter=500)
            if not result.converged:
                raise RuntimeError(f"AMG-preconditioned CG did not converge: {result}")
            return result.x
        return run


# ------------------------------------------------------------------------------ integrators
def _register_step_rows(backend: str) -> None:
    """One backward-Euler step of the clamped box from the deformed state
    (fem3d.solve.integrators)."""
    lib = f"fem3d-{backend}"

    @register(f"step/{lib}-implicit", group="step", library=f"{lib} implicit Euler",
              max_tets=1.1e5,
              note="step: fem3d.solve.integrators.implicit_euler, box clamped at z = 0, starting "
                   "at rest with velocity 10 (q - X), 5 Newton iterations at most.")
    def _step(mesh: BenchMesh):
        model = _fem3d_model(mesh, backend)
        integ = _import_fem3d("solve.integrators")
        cons = _import_fem3d("physics.constraints")
        fixed = np.flatnonzero(mesh.X[:, 2] <= mesh.X[:, 2].min() + 1e-12)
        c = cons.Constraints.from_fixed_vertices(mesh.X, fixed)
        system = integ.System(model, c)
        v0 = 10.0 * (mesh.q - mesh.X)  # a smooth velocity field, clamped vertices at rest
        v0[fixed] = 0.0
        state = integ.State(q=mesh.X.copy(), v=v0)
        return lambda: integ.implicit_euler(system, state, mesh.dt)


for _b in ("numpy", "c"):
    _register_kernel_rows(_b)
    _register_step_rows(_b)
for _s in ("cholmod", "pardiso", "superlu"):
    _register_solver_rows(_s)
_register_amg_rows()

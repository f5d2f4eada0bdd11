"""Peer of ``python -m bench.contact``: the same soft-body drop in NVIDIA Newton's VBD solver on
Warp's CPU device.

Newton (PyPI ``newton``, on ``warp-lang``) steps volumetric soft bodies with Vertex Block
Descent (Chen et al. 2024): a Gauss-Seidel sweep over graph-coloured vertices, each a 3x3
Newton step on the stable Neo-Hookean energy plus penalty contact (``soft_contact_ke``) and
friction. Its usual setup is many cheap substeps per frame: here 10 substeps x 10 iterations
per 0.01 s frame (the hanging soft-body example's counts), so one frame covers the time of one
fem3d step. Contact with the ground is a penalty on the vertex's sphere of
``particle_radius``: a vertex resting on the ground sits about that radius above it, and
the distance by which it gets lower than the radius is the penetration.

The timing leaves out Warp's kernel compilation (first use; cached in ``~/.cache/warp``): one
warm-up frame on the same model runs first, then the states are rebuilt at rest. Warp runs CPU
kernels on one thread. Anything that keeps Newton from running here (not installed, no CPU
device, an API change) raises :class:`bench.Skip` with the reason, never another exception.
"""

# No "from __future__ import annotations": Warp inspects annotations itself.

import time

import numpy as np

from bench import Skip

LIB = "newton-vbd-cpu"


def _import():
    try:
        import warp as wp
    except ImportError as err:
        raise Skip(f"warp-lang not installed ({err}); pip install newton") from err
    try:
        import newton
    except ImportError as err:
        raise Skip(f"newton not installed ({err}); pip install newton") from err
    return wp, newton


def drop(X: np.ndarray, T: np.ndarray, *, steps: int, dt: float = 0.01, E: float, nu: float,
         rho: float, mu: float, particle_radius: float, substeps: int = 10,
         iterations: int = 10, contact_ke: float = 2e6, contact_kd: float = 0.2) -> dict:
    """Drop the tet mesh ``(X, T)`` (y up) on the ground plane ``y = 0`` in Newton's VBD.

    Parameters
    ----------
    X : (n, 3) float
        Rest = initial positions (m), above the ground.
    T : (m, 4) int
        Tets.
    steps : int
        Frames of ``dt`` timed (each ``substeps`` VBD steps of ``iterations`` sweeps).
    E, nu, rho : float
        Young's modulus (Pa), Poisson ratio, density (kg/m^3); Newton takes the Lame
        parameters ``k_mu = E / (2 (1 + nu))``, ``k_lambda = E nu / ((1 + nu)(1 - 2 nu))``.
    mu : float
        Friction coefficient (body and ground).
    particle_radius : float
        The vertices' contact radius (m).
    contact_ke, contact_kd : float
        Contact penalty stiffness and damping (those of Newton's soft-body Franka example).

    Returns
    -------
    dict
        ``case``, ``library``, ``tets``, ``steps``, ``wall`` (s, timed frames), ``steps_per_s``
        (frames per second), ``lowest_gap`` (lowest vertex height over every frame, m),
        ``particle_radius``, ``compile_s`` (the warm-up frame, s).

    Raises
    ------
    Skip
        When Newton cannot be imported or run on Warp's CPU device (the reason).
    """
    wp, newton = _import()
    try:
        wp.config.quiet = True
        wp.init()
        with wp.ScopedDevice("cpu"):
            return _run(wp, newton, np.asarray(X, float), np.asarray(T, np.int64), steps, dt,
                        E, nu, rho, mu, particle_radius, substeps, iterations, contact_ke,
                        contact_kd)
    except Skip:
        raise
    except Exception as err:  # noqa: BLE001 - a peer that fails is a skipped row, not a crash
        raise Skip(f"newton {getattr(newton, '__version__', '?')} failed on the CPU: "
                   f"{type(err).__name__}: {err}") from err


def _run(wp, newton, X, T, steps, dt, E, nu, rho, mu, radius, substeps, iterations, ke, kd):
    k_mu = E / (2.0 * (1.0 + nu))
    k_lambda = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=(0.0, -9.81, 0.0))
    builder.add_soft_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0,
                          vel=wp.vec3(0.0, 0.0, 0.0), vertices=[wp.vec3(*p) for p in X],
                          indices=T.reshape(-1).tolist(), density=rho, k_mu=k_mu,
                          k_lambda=k_lambda, k_damp=0.0, particle_radius=radius)
    builder.add_ground_plane()
    builder.color()
    model = builder.finalize(device="cpu")
    model.soft_contact_ke, model.soft_contact_kd, model.soft_contact_mu = ke, kd, mu
    model.shape_material_ke.fill_(ke)
    model.shape_material_kd.fill_(kd)
    model.shape_material_mu.fill_(mu)
    solver = newton.solvers.SolverVBD(model=model, iterations=iterations,
                                      particle_enable_self_contact=False,
                                      particle_enable_tile_solve=False)
    pipeline = newton.CollisionPipeline(model)
    contacts = pipeline.contacts()
    control = model.control()
    h = dt / substeps

    def frame(s0, s1):
        for _ in range(substeps):
            s0.clear_forces()
            pipeline.collide(s0, contacts)
            solver.step(s0, s1, control, contacts, h)
            s0, s1 = s1, s0
        return s0, s1

    t0 = time.perf_counter()
    frame(model.state(), model.state())  # compiles the kernels
    compile_s = time.perf_counter() - t0
    s0, s1 = model.state(), model.state()
    lowest = np.inf
    t0 = time.perf_counter()
    for _ in range(steps):
        s0, s1 = frame(s0, s1)
        q = s0.particle_q.numpy()
        if not np.isfinite(q).all():
            raise Skip("newton's VBD state became non-finite")
        lowest = min(lowest, float(q[:, 1].min()))
    wall = time.perf_counter() - t0
    return {"case": f"bunny_drop [{LIB}, {substeps}x{iterations}]", "library": LIB,
            "tets": int(len(T)), "steps": steps, "wall": wall, "steps_per_s": steps / wall,
            "lowest_gap": lowest, "particle_radius": radius, "compile_s": compile_s,
            "newton_version": getattr(newton, "__version__", "?")}

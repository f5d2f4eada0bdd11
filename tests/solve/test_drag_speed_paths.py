"""The interactive drag's speed paths: the extrapolated Newton start (``warm_start``) and the
linear solver's handling of the Newton matrices it is given (no timing asserted here: the
figures are ``python -m bench.newton_step``'s)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from fem3d.solve.integrators import System, implicit_euler
from fem3d.solve.linear.base import as_csr
from fem3d.solve.settings import NewtonSettings


@pytest.fixture(scope="module")
def drag():
    """The classic armadillo (627 tets) with its hand dragged out and round (bench)."""
    from bench.newton_step import armadillo

    return armadillo(0, 40)


def _run(work, warm_start: str, steps: int):
    system = System(work.model, work.constraints)
    state, newton, states = work.start, 0, []
    for pull in work.pulls[:steps]:
        state, stats = implicit_euler(system, state, work.dt, pull, max_iterations=None,
                                      linear_solver="reuse", warm_start=warm_start)
        assert stats.converged
        assert stats.gradient_norms[-1] <= stats.gradient_tolerance
        newton += stats.newton_iterations
        states.append(state)
    return states, newton


def test_extrapolated_start_keeps_the_tolerance_with_fewer_newton_iterations(drag):
    """``warm_start="extrapolate"``: every step still ends below its gradient tolerance, on
    the classic start's trajectory (to the tolerance's level), in fewer Newton iterations;
    each state carries the one before it; the first step (no history) is the classic one."""
    plain, n_plain = _run(drag, "previous", 36)
    warm, n_warm = _run(drag, "extrapolate", 36)
    assert n_warm < 0.9 * n_plain
    assert np.array_equal(warm[0].q, plain[0].q) and np.array_equal(warm[0].v, plain[0].v)
    assert "v_prev" not in plain[-1].history  # the classic start keeps no history
    for before, after in zip(warm, warm[1:], strict=False):
        assert after.history["v_prev"] is before.v and after.history["q_prev"] is before.q
    deviation = max(float(np.abs(a.q - b.q).max()) for a, b in zip(warm, plain, strict=True))
    assert deviation < 1e-6 * drag.size


def test_a_worse_extrapolation_is_not_taken(drag):
    """A history whose extrapolation has more energy than ``v_t`` leaves the classic start:
    the step is bit for bit the classic step."""
    system = System(drag.model, drag.constraints)
    state = drag.start
    for pull in drag.pulls[:6]:
        state, _ = implicit_euler(system, state, drag.dt, pull, max_iterations=None,
                                  linear_solver="reuse")
    # v_prev far off: 2 v - v_prev flings every free vertex
    wild = state.with_history(v_prev=state.v - 50.0)
    steps = {}
    for name, start, warm in (("plain", state, "previous"), ("wild", wild, "extrapolate")):
        system = System(drag.model, drag.constraints)
        steps[name], _ = implicit_euler(system, start, drag.dt, drag.pulls[6],
                                        max_iterations=None, linear_solver="direct",
                                        warm_start=warm)
    assert np.array_equal(steps["wild"].q, steps["plain"].q)
    assert np.array_equal(steps["wild"].v, steps["plain"].v)
    assert steps["wild"].history["v_prev"] is state.v


def test_unknown_warm_start_is_refused():
    with pytest.raises(ValueError, match="warm_start must be one of previous, extrapolate"):
        NewtonSettings(warm_start="quadratic")


def test_as_csr_keeps_a_float64_csr_matrix_and_copies_anything_else():
    """A float64 CSR matrix is used as it is (its canonical-format check is cached on it);
    other input is converted, duplicates summed, the input left alone."""
    A = sp.csr_matrix(np.array([[2.0, -1.0], [-1.0, 2.0]]))
    assert as_csr(A) is A
    coo = sp.coo_matrix((np.array([1.0, 1.0, 3.0]), (np.array([0, 0, 1]), np.array([0, 0, 1]))),
                        shape=(2, 2))
    B = as_csr(coo)
    assert isinstance(B, sp.csr_matrix) and B.has_canonical_format
    assert np.array_equal(B.toarray(), [[2.0, 0.0], [0.0, 3.0]])
    assert coo.nnz == 3
    C = sp.csr_matrix((np.array([1.0, 1.0]), np.array([0, 0]), np.array([0, 2, 2])),
                      shape=(2, 2))  # a duplicate entry: not canonical
    D = as_csr(C)
    assert D is not C and D.nnz == 1 and C.nnz == 2
    assert as_csr(A.astype(np.float32)).dtype == np.float64


def test_contact_keeps_the_classic_start():
    """With contact (CCD-limited, stiff-barrier terms) ``"extrapolate"`` keeps the classic
    start: the falling bunny's steps are bit for bit the classic ones, the history carried."""
    from fem3d.scene import load_scene
    from fem3d.simulation import Simulation
    from fem3d.solve.schemes.implicit import IMPLICIT

    finals = {}
    for warm in ("previous", "extrapolate"):
        sim = Simulation(load_scene("contact_bunny_drop"), scripted=True)
        state = sim.state
        for _ in range(8):
            state, _ = IMPLICIT.step(sim.system, sim.objective_terms(), state, sim.dt,
                                     NewtonSettings(max_iterations=None, solver="reuse",
                                                    warm_start=warm))
        finals[warm] = state
    assert finals["extrapolate"].history["v_prev"] is not None
    assert np.array_equal(finals["extrapolate"].q, finals["previous"].q)
    assert np.array_equal(finals["extrapolate"].v, finals["previous"].v)


def test_the_scene_key_reaches_the_step_and_is_refused_where_it_does_not_apply():
    from fem3d.scene import apply_overrides, load_scene
    from fem3d.simulation import Simulation

    scene = apply_overrides(load_scene("arma"), {"simulation.newton.warm_start": "extrapolate",
                                                 "simulation.integrator": "implicit"})
    plain = Simulation(load_scene("arma"), scripted=True)
    warm = Simulation(scene, scripted=True)
    assert warm.newton.warm_start == "extrapolate" and plain.newton.warm_start == "previous"
    iterations = {"plain": 0, "warm": 0}
    for name, sim in (("plain", plain), ("warm", warm)):
        for _ in range(30):  # the pull's smooth drag: the extrapolated start saves iterations
            sim.step()
            iterations[name] += sim.last_stats.newton_iterations
    assert iterations["warm"] < iterations["plain"]
    scale = float(np.ptp(plain.q, axis=0).max())
    assert np.abs(warm.q - plain.q).max() < 1e-6 * scale  # the same solution to tolerance
    with pytest.raises(Exception, match="warm_start.*implicit"):
        apply_overrides(load_scene("arma"), {"simulation.newton.warm_start": "extrapolate",
                                             "simulation.integrator": "bdf2"})

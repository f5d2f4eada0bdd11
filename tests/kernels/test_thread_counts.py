"""Per-family thread counts of the threaded C kernels (fem3d.kernels.threads): the override,
the measured choice, the report, and the same bits whatever count is chosen."""

from __future__ import annotations

import io

import numpy as np
import pytest

import fem3d.kernels.threads as threads
from fem3d.app.profile import profiled
from fem3d.errors import InputError
from fem3d.kernels.backend import c_extension


@pytest.fixture(autouse=True)
def _fresh_policy(monkeypatch):
    """Every test starts and ends without choices, FEM3D_THREADS unset and OpenMP's count
    restored."""
    monkeypatch.delenv(threads.ENV, raising=False)
    ext = c_extension()
    before = ext.max_threads() if ext is not None else 1
    threads.reset()
    yield
    threads.reset()
    if ext is not None:
        ext.set_max_threads(before)


def _fake_machine(monkeypatch, available: int) -> None:
    monkeypatch.setattr(threads, "available_threads", lambda: available)


class _Clock:
    """A fake ``time.perf_counter`` the trials advance (timings without a real machine's
    noise)."""

    def __init__(self, monkeypatch):
        self.now = 0.0
        monkeypatch.setattr(threads.time, "perf_counter", lambda: self.now)

    def sleep(self, seconds: float) -> None:
        self.now += seconds


def _timed(clock, calls: list, one: float, many: float):
    """A trial that records its thread count and takes ``one`` s on 1 thread, else ``many``."""
    def trial(n):
        calls.append(n)
        clock.sleep(one if n == 1 else many)
    return trial


def test_the_override_parses_counts_and_families(monkeypatch):
    for value, expected in [("", None), ("auto", None), ("3", 3), (" 1 ", 1),
                            ("solve=1,products=2", 1), ("products=2", None),
                            ("solve=auto,products=2", None)]:
        monkeypatch.setenv(threads.ENV, value)
        assert threads.forced_threads("solve") == expected, value
    monkeypatch.setenv(threads.ENV, "solve=1,products=2")
    assert threads.forced_threads("products") == 2
    for bad in ("0", "two", "-1", "sweep=1", "solve=0", "solve", "solve=1,,"):
        monkeypatch.setenv(threads.ENV, bad)
        with pytest.raises(InputError, match=rf"^{threads.ENV}='{bad}': "):
            threads.forced_threads("solve")


def test_a_forced_count_is_capped_by_openmp_and_reported(monkeypatch):
    _fake_machine(monkeypatch, 2)
    monkeypatch.setenv(threads.ENV, "products=8,solve=1")
    ran = []
    assert threads.measure("products", ran.append) == 2  # capped at OpenMP's 2
    assert threads.measure("solve", ran.append) == 1
    assert ran == []  # forced: nothing measured
    lines = threads.report().splitlines()
    assert lines[1].strip() == ("AMG setup Galerkin products: 2 of 2 threads (forced by "
                                "FEM3D_THREADS=products=8,solve=1)")
    assert "dot products): 1 of 2 threads" in lines[2]


@pytest.mark.parametrize("faster", [1, 4])
def test_the_measured_choice_keeps_the_faster_count(monkeypatch, faster):
    clock = _Clock(monkeypatch)
    _fake_machine(monkeypatch, 4)
    calls = []

    def trial(n):  # the faster count takes 1 ms, the other 6 ms
        calls.append(n)
        clock.sleep(0.001 if n == faster else 0.006)

    monkeypatch.setattr(threads, "MIN_MEASURE_SECONDS", 0.0)
    assert threads.measure("products", trial, repeats=2) == faster
    # a warm-up, then alternately (a clear loss of 4 threads: one round only)
    assert calls == ([4, 1, 4] if faster == 1 else [4, 1, 4, 1, 4])
    made = len(calls)
    assert threads.measure("products", trial) == faster and len(calls) == made  # cached
    (choice,) = threads.choices()
    assert choice.how == "measured" and choice.available == 4 and choice.threads == faster
    assert f"{faster} of 4 threads (measured" in choice.line()
    threads.reset()
    assert threads.choices() == [] and threads.measure("products", trial) == faster


def test_an_equal_time_keeps_one_thread_and_short_trials_repeat(monkeypatch):
    clock = _Clock(monkeypatch)
    _fake_machine(monkeypatch, 2)
    calls = []
    trial = _timed(clock, calls, 0.001, 0.001)
    assert threads.measure("solve", trial) == 1  # equal within MARGIN: one thread
    assert len(calls) >= 1 + 2 * 3 and len(calls) <= 1 + 2 * threads.MAX_ROUNDS


def test_adaptive_measures_on_the_calls_themselves(monkeypatch):
    clock = _Clock(monkeypatch)
    _fake_machine(monkeypatch, 2)
    counts = []

    def run(n):
        counts.append(n)
        clock.sleep(0.004 if n == 1 else 0.001)
        return n

    threads.adaptive("assembly x.hessian", "assembly", run)
    assert threads.report().splitlines()[1] == ("  fused assembly x.hessian: still measuring "
                                                "after 1 call (4.00 ms on 1)")
    results = [1] + [threads.adaptive("assembly x.hessian", "assembly", run) for _ in range(5)]
    assert counts == [1, 2, 1, 2, 2, 2] and results == counts
    assert threads.choices()[0].key == "assembly x.hessian"
    assert "fused assembly x.hessian: 2 of 2 threads" in threads.report()
    counts.clear()
    loses = _timed(clock, counts, 0.001, 0.005)  # a clear loss: one pair of calls measured
    for _ in range(4):
        threads.adaptive("assembly x.energy", "assembly", loses)
    assert counts == [1, 2, 1, 1]


def test_a_clear_loss_stops_measuring_early(monkeypatch):
    clock = _Clock(monkeypatch)
    _fake_machine(monkeypatch, 2)
    calls = []
    trial = _timed(clock, calls, 0.001, 0.005)
    assert threads.measure("products", trial) == 1 and calls == [2, 1, 2]


def test_one_available_thread_measures_nothing(monkeypatch):
    _fake_machine(monkeypatch, 1)
    assert threads.measure("solve", lambda n: pytest.fail("measured")) == 1
    assert threads.choices()[0].how == "single"


def test_unknown_family_is_refused():
    with pytest.raises(ValueError, match="unknown kernel family 'gpu'"):
        threads.measure("gpu", lambda n: None)


def test_the_profile_lists_the_choices_made_during_the_run(monkeypatch):
    _fake_machine(monkeypatch, 2)
    # the no-op trials' times are noise: a "clear loss" of two threads must not end the
    # x.energy measurement early (under load it did, and its choice was then listed)
    monkeypatch.setattr(threads, "CLEAR_LOSS", float("inf"))
    monkeypatch.setenv(threads.ENV, "1")
    threads.measure("products", lambda n: None)  # before the run: not listed
    monkeypatch.setenv(threads.ENV, "solve=1")
    threads.adaptive("assembly x.energy", "assembly", lambda n: None)  # begun before: neither
    out = io.StringIO()
    with profiled(out=out):
        threads.measure("solve", lambda n: None)
        threads.adaptive("assembly x.energy", "assembly", lambda n: None)
        threads.adaptive("assembly x.hessian", "assembly", lambda n: None)
    text = out.getvalue()
    assert text.splitlines()[-3] == ("threads per kernel family (fem3d.kernels.threads; "
                                     "FEM3D_THREADS forces them):")
    assert text.splitlines()[-2] == ("  AMG-PCG solve (Gauss-Seidel sweeps, mat-vecs, dot "
                                     "products): 1 of 2 threads (forced by "
                                     "FEM3D_THREADS=solve=1)")
    assert text.splitlines()[-1].startswith("  fused assembly x.hessian: still measuring after "
                                            "1 call (")
    assert "Galerkin" not in text and "x.energy" not in text
    out = io.StringIO()
    with profiled(out=out):
        pass
    assert "threads per kernel family" not in out.getvalue()


# --- the real kernels: the same bits on any chosen count ------------------------------------

needs_c = pytest.mark.skipif(c_extension() is None or not c_extension().OPENMP,
                             reason="C extension with OpenMP not built")


@needs_c
def test_forced_one_and_two_threads_give_the_same_amg_solve(monkeypatch):
    pytest.importorskip("pyamg")
    from tests.solve.test_amg import _threaded_setup

    c_extension().set_max_threads(2)
    b = np.random.default_rng(1).standard_normal(3 * 15**3)
    results = []
    for forced in ("1", "2", "auto"):
        monkeypatch.setenv(threads.ENV, forced)
        threads.reset()
        A, amg, _ = _threaded_setup()
        res = amg.solve(A, b[:A.shape[0]], rtol=1e-8, maxiter=100)
        results.append((amg.apply(b[:A.shape[0]]), res.x, res.iterations))
        if forced != "auto":
            assert amg.thread_counts == dict.fromkeys(("products", "solve"), int(forced))
        else:  # measured: a valid count per family
            assert set(amg.thread_counts) == {"products", "solve"}
            assert set(amg.thread_counts.values()) <= {1, 2}
            assert {c.how for c in threads.choices()} == {"measured"}
    (z1, x1, it1), *others = results
    for z, x, it in others:
        assert np.array_equal(z1, z) and np.array_equal(x1, x) and it1 == it


@needs_c
def test_forced_one_and_two_threads_give_the_same_fused_assembly(monkeypatch):
    from fem3d.kernels.schedule import PARALLEL_MIN_TETS
    from fem3d.mesh.tetmesh import box_tet_mesh
    from fem3d.physics.model import build_model

    X, T = box_tet_mesh((24, 16, 15))  # 34,560 tets: threaded
    assert len(T) >= PARALLEL_MIN_TETS
    model = build_model(X, T, E=1e5, nu=0.4, rho=1000.0, backend="c")
    q = X * 1.05 + 0.01 * np.random.default_rng(3).standard_normal(X.shape)
    c_extension().set_max_threads(2)
    outs = []
    for forced in ("1", "2", "auto"):
        monkeypatch.setenv(threads.ENV, forced)
        threads.reset()
        for _ in range(5):  # auto: alternately 1 and 2 threads, then the faster
            out = np.zeros(model.nnz)  # the Newton matrix's values
            model.mat.hessian_assemble(q, model.T, model.dphi_dX, model.vol, model.params,
                                       model.scatter, out)
            outs.append(out)
        (choice,) = threads.choices()
        assert choice.key == f"assembly {model.mat.name}.hessian"
        assert choice.threads in (1, 2) and (forced == "auto" or choice.threads == int(forced))
    for out in outs[1:]:
        assert np.array_equal(outs[0], out)


@needs_c
def test_the_c_kernels_refuse_a_bad_thread_count():
    ext = c_extension()
    name = next(n for n in dir(ext) if n.endswith("_assemble"))
    with pytest.raises(TypeError, match="n_threads"):
        getattr(ext, name)(*([None] * 3))
    x = np.ones(4)
    y = np.empty(2)
    indptr = np.array([0, 1, 2], dtype=np.int32)
    indices = np.array([0, 3], dtype=np.int32)
    data = np.array([2.0, 3.0])
    for n in (0, 1, 2, 64):  # any count (capped at OpenMP's), the same result
        ext.csr_matvec(indptr, indices, data, x, y, n)
        assert y.tolist() == [2.0, 3.0] and ext.dot(x, x, n) == 4.0


@needs_c
def test_fem3d_run_profile_reports_the_counts_and_refuses_a_bad_override(tmp_path, monkeypatch,
                                                                          capsys):
    """What the user sees: ``fem3d run --profile`` on a mesh above the threaded-assembly size
    lists the counts below its stage table; a bad FEM3D_THREADS is one line, status 2."""
    from fem3d.app.cli import main
    from fem3d.mesh.formats import write_tet_mesh
    from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh

    mesh = tmp_path / "box.mesh"
    write_tet_mesh(mesh, TetMesh(*box_tet_mesh((24, 16, 15), size=(3.0, 2.0, 2.0))))
    run = ["run", str(mesh), "--steps", "1", "--quiet", "--no-preview", "--profile"]
    monkeypatch.setenv(threads.ENV, "assembly=1")
    assert main([*run, "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    policy = err.split("threads per kernel family", 1)[1]
    assert ".energy: 1 of " in policy and "(forced by FEM3D_THREADS=assembly=1)" in policy
    threads.reset()
    monkeypatch.setenv(threads.ENV, "assembly=lots")
    assert main([*run, "--out", str(tmp_path / "b")]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
    assert lines == ["fem3d run: error: FEM3D_THREADS='assembly=lots': a thread count must be "
                     "'auto' or a whole number >= 1, got 'lots'"]

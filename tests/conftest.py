"""Suite-wide checks: what CI requires to be present (``FEM3D_REQUIRE_C``).

The C extension is built ``optional=True`` so that ``pip install`` works without a compiler;
the C-back-end tests then skip. CI sets ``FEM3D_REQUIRE_C=1`` (see ``.ci/run``) so that a
failed build fails the run instead of silently skipping about 140 tests.
"""

from __future__ import annotations

import fcntl
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

# One BLAS thread in this process and in every fem3d process a test starts (they inherit the
# environment): a trajectory's bits depend on OpenBLAS's thread count (cantilever_amg parts
# between 1 and 2 threads), and tests/simulation/test_determinism.py compares this process's
# runs with another process's bit for bit. Set before NumPy loads OpenBLAS; a caller's own
# setting wins.
if "numpy" not in sys.modules:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest  # noqa: E402

from fem3d.kernels.backend import c_extension  # noqa: E402


def missing_required_c(environ=os.environ, extension=c_extension) -> str | None:
    """Why the suite must not run, or ``None``.

    Parameters
    ----------
    environ : mapping
        The environment; ``FEM3D_REQUIRE_C=1`` requires the extension.
    extension : callable
        Returns the loaded extension or ``None`` (:func:`fem3d.kernels.backend.c_extension`).

    Returns
    -------
    str or None
        The reason when the extension is required and not importable.
    """
    if environ.get("FEM3D_REQUIRE_C") != "1" or extension() is not None:
        return None
    return ("FEM3D_REQUIRE_C=1 but the C extension fem3d._ckernels is not importable: "
            "build it with `pip install -e .` (a C compiler is needed)")


def pytest_sessionstart(session):
    """Stop the whole run when a required back end is missing (CI must not go green)."""
    reason = missing_required_c()
    if reason is not None:
        raise pytest.UsageError(reason)


# -- many workers (make test: pytest-xdist, whole files per worker) ---------------------------
# A test marked ``alone`` runs while no other worker's test runs: its mpiexec ranks wait for
# each other by polling, and a test beside them on the same cores makes a 3 s two-rank run
# take 40-60 s (measured with two workers on 2 cores). The ``browser`` tests run alone too:
# the viewer steps at the wall clock's rate and the page must follow a drag within its wait
# (beside another worker's test it once did not, and once the worker died in that test).
# The other tests share the cores.
# A readers-writer lock over two files, fair to the writer: every test passes the turnstile
# first, and an ``alone`` test holds it while it waits for the running tests to end.


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: one worker more than cores. A test often waits (on a subprocess it
    started, a socket, a browser page, a Dask worker's start), and a third worker fills
    those waits: on 2 cores the 1760 tests that are neither ``alone`` nor ``browser`` took
    276 s on 3 workers, 295 s on 2 (docs/testing.md)."""
    return (os.cpu_count() or 1) + 1


@contextmanager
def _flock(path: Path, mode: int) -> Iterator[None]:
    with open(path, "a") as f:
        fcntl.flock(f, mode)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


#: this worker's turns on the cores, innermost last (True: alone)
_HELD: list[bool] = []


@contextmanager
def cores(tmp_path_factory: pytest.TempPathFactory, alone: bool) -> Iterator[None]:
    """The cores, shared with the other workers' tests or (``alone``) to this test alone;
    a no-op without workers. A module fixture that launches ``mpiexec`` takes them alone
    itself: it is set up before its first test's own (autouse) turn. Within a turn this
    worker holds, a turn it already has is a no-op (the lock files would wait for their own
    holder), and asking for the cores alone inside a shared turn is an error, not a hang."""
    if "PYTEST_XDIST_WORKER" not in os.environ or (_HELD and (any(_HELD) or not alone)):
        yield
        return
    if _HELD:
        raise RuntimeError("cores(alone=True) inside a test that shares the cores would wait "
                           "for itself: mark the test alone")
    folder = tmp_path_factory.getbasetemp().parent  # the one every worker's folder is in
    turnstile, pool = folder / "fem3d-turnstile.lock", folder / "fem3d-cores.lock"
    _HELD.append(alone)
    try:
        if alone:
            with _flock(turnstile, fcntl.LOCK_EX), _flock(pool, fcntl.LOCK_EX):
                yield
            return
        with _flock(turnstile, fcntl.LOCK_EX):
            pass
        with _flock(pool, fcntl.LOCK_SH):
            yield
    finally:
        _HELD.pop()


@pytest.fixture(autouse=True)
def _share_the_cores(request: pytest.FixtureRequest,
                     tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    marked = request.node.get_closest_marker("alone") or request.node.get_closest_marker("browser")
    with cores(tmp_path_factory, alone=bool(marked)):
        yield


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Files with ``slow`` or ``browser`` tests first (the longest first is the shortest
    schedule when workers take whole files; a browser test waits on the page while the
    other worker computes); the rest in their usual order."""
    slow = {item.path for item in items
            if item.get_closest_marker("slow") or item.get_closest_marker("browser")}
    items.sort(key=lambda item: item.path not in slow)

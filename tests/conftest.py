"""Suite-wide checks: what CI requires to be present (``FEM3D_REQUIRE_C``).

The C extension is built ``optional=True`` so that ``pip install`` works without a compiler;
the C-back-end tests then skip. CI sets ``FEM3D_REQUIRE_C=1`` (see ``.ci/run``) so that a
failed build fails the run instead of silently skipping about 140 tests.
"""

from __future__ import annotations

import os
import sys

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

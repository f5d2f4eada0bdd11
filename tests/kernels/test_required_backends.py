"""What CI requires: the C extension under ``FEM3D_REQUIRE_C=1``, and the public imports."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from fem3d.kernels.backend import c_extension
from tests.conftest import missing_required_c

ROOT = Path(__file__).resolve().parents[2]


def test_required_c_reason_only_when_required_and_missing():
    assert missing_required_c({}, lambda: None) is None
    assert missing_required_c({"FEM3D_REQUIRE_C": "1"}, lambda: object()) is None
    reason = missing_required_c({"FEM3D_REQUIRE_C": "1"}, lambda: None)
    assert reason is not None and "fem3d._ckernels" in reason


def test_c_extension_present_when_required():
    """Fails (never skips) when CI requires the extension and it is not importable."""
    if os.environ.get("FEM3D_REQUIRE_C") == "1":
        assert c_extension() is not None, "FEM3D_REQUIRE_C=1 but fem3d._ckernels is missing"
    elif c_extension() is None:
        pytest.skip("C extension not built (CI sets FEM3D_REQUIRE_C=1 to make this fail)")


def test_pytest_run_fails_when_required_c_is_missing(tmp_path):
    """A whole pytest run exits non-zero when the extension is blocked and required."""
    block = tmp_path / "block"
    block.mkdir()
    # a meta-path finder that refuses fem3d._ckernels, installed before pytest starts
    (block / "sitecustomize.py").write_text(
        "import sys\n"
        "class _Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'fem3d._ckernels':\n"
        "            raise ImportError('blocked by the test')\n"
        "sys.meta_path.insert(0, _Block())\n")
    path = os.pathsep.join([str(block), str(ROOT), os.environ.get("PYTHONPATH", "")])
    env = dict(os.environ, FEM3D_REQUIRE_C="1", PYTHONPATH=path)
    target = ("kernels/test_required_backends.py"
              "::test_required_c_reason_only_when_required_and_missing")
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
         str(ROOT / "tests" / target)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert "FEM3D_REQUIRE_C=1" in proc.stdout + proc.stderr


def test_an_extension_older_than_generated_is_one_line(monkeypatch):
    """A C extension built before generated/ gained a kernel (an editable checkout updated
    without a rebuild): one line naming the kernel and the rebuild, not an AttributeError."""
    from types import SimpleNamespace

    from fem3d.errors import InputError
    from fem3d.kernels import dispatch

    monkeypatch.setattr(dispatch, "c_extension", lambda: SimpleNamespace())
    with pytest.raises(InputError, match=r"have no tet\.rest_shape: they are older than "
                                         r"generated/; rebuild them \(pip install -e \."):
        dispatch.KernelModule("tet", "c")


def test_public_entry_points_import_from_the_package():
    from fem3d import Scene, Simulation, load_scene, run_scene
    from fem3d.app.run import run_scene as run_scene_impl
    from fem3d.scene import load_scene as load_scene_impl
    from fem3d.simulation import Simulation as simulation_impl

    assert Simulation is simulation_impl and load_scene is load_scene_impl
    assert run_scene is run_scene_impl and Scene is not None
    scene = load_scene("bunny")
    assert scene.bodies, "the built-in bunny scene loads through the public import"

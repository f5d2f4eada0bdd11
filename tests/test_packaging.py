"""What the wheel ships: every runtime subpackage and the built-in scenes with the meshes they
name (package data ``fem3d._data``), so an installed ``fem3d run bunny`` works from any folder.
The full check (build the wheel, install it into a fresh venv, run it outside the checkout) is
``scripts/check_wheel.sh``, a step of ``.ci/run``."""

from __future__ import annotations

import fnmatch
import re
import tomllib
from pathlib import Path

from fem3d.scene import load_scene
from fem3d.scene.load import data_dir, scene_names

ROOT = Path(__file__).resolve().parent.parent
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_runtime_package_is_in_the_wheel() -> None:
    found = {".".join(p.parent.relative_to(ROOT).parts)
             for p in (ROOT / "fem3d").rglob("__init__.py")}
    missing = found - set(CONFIG["packages"])
    assert not missing, f"pyproject's packages leave out {sorted(missing)}"


def _shipped(rel: str) -> bool:
    """``rel`` (a path under data/) matches a package-data glob (``*`` stays in a folder)."""
    return any(fnmatch.fnmatch(rel, pat) and rel.count("/") == pat.count("/")
               for pat in CONFIG["package-data"]["fem3d._data"])


def test_package_data_holds_every_scene_and_the_files_it_names() -> None:
    assert CONFIG["package-dir"]["fem3d._data"] == "data" and "fem3d._data" in CONFIG["packages"]
    data = ROOT / "data"
    names = scene_names()
    assert {"bunny", "arma", "contact_bunny_drop"} <= set(names)
    for name in names:
        scene = load_scene(name)
        files = [Path(scene.source)] + [scene.path(b.mesh) for b in scene.bodies]
        files += [scene.path(b.skin) for b in scene.bodies if b.skin]
        files += [scene.path(o.mesh.path) for o in scene.obstacles if o.mesh is not None]
        if any(f.suffix == ".node" for f in files):
            files += [f.with_suffix(".ele") for f in files if f.suffix == ".node"]
        for f in files:
            rel = f.resolve().relative_to(data.resolve()).as_posix()
            assert _shipped(rel), f"{name}: {rel} is not package data of fem3d._data"
    for sweep in (data / "sweeps").glob("*.toml"):
        assert _shipped(sweep.relative_to(data).as_posix())


def test_data_dir_is_the_checkout_or_the_installed_copy(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv("FEM3D_DATA", raising=False)
    assert data_dir() == ROOT / "data"  # a checkout (or an editable install) uses data/
    text = (ROOT / "fem3d" / "scene" / "load.py").read_text()
    assert re.search(r'parents\[1\] / "_data"', text), "no fallback to the installed copy"
    monkeypatch.setenv("FEM3D_DATA", str(tmp_path))
    assert data_dir() == tmp_path

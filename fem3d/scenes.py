"""Deprecated alias of :mod:`fem3d.scene.arrays`.

Moved in the restructuring of fem3d 0.2; the alias goes in 0.3 (see docs/architecture.md).
"""

from fem3d._deprecated import forward

__getattr__ = forward(__name__, (
    "fem3d.scene.arrays, fem3d.scene.load, fem3d.scene.build"), renamed={
    "assemble": "fem3d.scene.arrays.build_arrays",
    "Assembled": "fem3d.scene.arrays.SceneArrays",
    "ResolvedPull": "fem3d.scene.arrays.ScriptedPull",
})

"""Tet meshes: the mesh and its checks (:mod:`.tetmesh`), the finite elements as objects
(:mod:`.element`: P1, P2, their registry), quadratic meshes (:mod:`.quadratic`: lifting,
10-node files), file formats (:mod:`.formats`), display-mesh skinning (:mod:`.skin`) and
surfaces tetrahedralized by fTetWild (:mod:`.tetrahedralize`).

Names imported from ``fem3d.mesh`` itself (the module it was before 0.2) still resolve, with a
DeprecationWarning, until 0.3.
"""

from fem3d._deprecated import forward

__getattr__ = forward(__name__, "fem3d.mesh.formats, fem3d.mesh.tetmesh, fem3d.mesh.skin")

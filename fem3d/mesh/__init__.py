"""Tet meshes: the mesh and its checks (:mod:`.tetmesh`), file formats (:mod:`.formats`, one
module per reader family), display-mesh skinning (:mod:`.skin`) and surfaces tetrahedralized by
fTetWild (:mod:`.tetrahedralize`).
"""

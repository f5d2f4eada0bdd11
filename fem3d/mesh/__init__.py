"""Tet meshes: the mesh and its checks (:mod:`.tetmesh`), the finite elements as objects
(:mod:`.element`: P1, P2, their registry), quadratic meshes (:mod:`.quadratic`: lifting,
10-node files), file formats (:mod:`.formats`, one module per reader family), display-mesh
skinning (:mod:`.skin`) and surfaces tetrahedralized by fTetWild (:mod:`.tetrahedralize`).
"""

"""Tet meshes: the mesh itself and its checks (:mod:`.tetmesh`), file formats
(:mod:`.formats`), display-mesh skinning (:mod:`.skin`) and surfaces tetrahedralized by
fTetWild (:mod:`.tetrahedralize`)."""

"""Tet meshes: formats (:mod:`.formats`), display-mesh skinning (:mod:`.skin`) and surfaces
tetrahedralized by fTetWild (:mod:`.tetrahedralize`)."""

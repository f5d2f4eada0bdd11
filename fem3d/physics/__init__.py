"""The discretised physics: model (mesh, material, mass, sparsity), materials, assembly,
constraints, pin motions, contact and the objective terms."""

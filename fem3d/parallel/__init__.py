"""One simulation on several MPI ranks through PETSc (``mpiexec -n N fem3d run scene.toml``).

The road, each stage a module:

* :mod:`~fem3d.parallel.comm`: whether this process is one of several MPI ranks, the
  communicator, and sums every rank agrees on bit for bit;
* :mod:`~fem3d.parallel.partition`: the tets split by PETSc's graph partitioner (PT-Scotch or
  ParMETIS) on their face-adjacency graph, the vertices given to the lowest rank among their
  tets, and the free DOFs numbered rank by rank (:class:`~fem3d.solve.linear.petsc.
  DofLayout`; :func:`~fem3d.parallel.partition.local_layout` over a rank's local free DOFs);
* :mod:`~fem3d.parallel.ghosts`: :class:`~fem3d.parallel.ghosts.Ghosts`, the entries of a
  rank-local vector other ranks hold too: their partial sums added in rank order
  (``assemble``) and the ghosts given their owners' values (``complete``);
* :mod:`~fem3d.parallel.local`: a rank's own model, the model of its tets alone (the same
  generated kernels, materials, mass and damping), over the whole vertex numbering, made
  from the whole model while the scene is built (:class:`~fem3d.parallel.run.RankShare`),
  which is let go before the system is built;
* :mod:`~fem3d.parallel.system`: :class:`DistributedSystem`, a
  :class:`~fem3d.solve.system.System` on the local model whose terms sum their energies and
  gradients over the ranks and whose Newton matrices (and Newmark's mass matrix) go into one
  distributed PETSc matrix (:class:`~fem3d.solve.linear.petsc.PetscSolver`): the
  integrators, the objective, Newton's line search and stopping rule run unchanged, the
  same on every rank;
* :mod:`~fem3d.parallel.run`: the run loop of ``fem3d run`` and ``fem3d resume`` under
  ``mpiexec``: ``energy.csv`` and the one-process ``checkpoint.npz`` from rank 0 (resumable
  on any rank count), frames by :mod:`~fem3d.parallel.pieces` (one ``.vtu`` piece per rank,
  a ``.pvtu`` per frame and a ``.pvd``).

docs/parallel.md says what runs, how, and what it measured.
"""

"""One simulation on several MPI ranks through PETSc (``mpiexec -n N fem3d run scene.toml``).

The road, each stage a module:

* :mod:`~fem3d.parallel.comm`: whether this process is one of several MPI ranks, the
  communicator, and sums every rank agrees on bit for bit;
* :mod:`~fem3d.parallel.partition`: the tets split by METIS on rank 0 (or PETSc's graph
  partitioner) on their face-adjacency graph, and the free DOFs numbered rank by rank
  (:func:`~fem3d.parallel.partition.local_layout`: a :class:`~fem3d.solve.linear.petsc.
  DofLayout` over a rank's local free DOFs);
* :mod:`~fem3d.parallel.ghosts`: :class:`~fem3d.parallel.ghosts.Ghosts`, the entries of a
  rank-local vector other ranks hold too, each owned by the lowest rank holding it: their
  partial sums added in rank order (``assemble``) and the ghosts given their owners' values
  (``complete``);
* :mod:`fem3d.scene.local` (with :func:`fem3d.scene.build.build`'s ``restrict``): a rank's
  share of the scene over the vertices of its own tets, the model built of its tets alone
  (the same generated kernels, materials, mass and damping), the pins, motions, loads and
  pulls of the whole scene's selections carried into its numbering;
* :mod:`~fem3d.parallel.system`: :class:`DistributedSystem`, a
  :class:`~fem3d.solve.system.System` on the local model and rank-local vectors whose terms
  sum their energies over the ranks and their gradients over the ghosts, whose Newton
  reductions count the owned entries (:class:`~fem3d.parallel.system.OwnedReductions`), and
  whose Newton matrices (and Newmark's mass matrix) go into one distributed PETSc matrix
  (:class:`~fem3d.solve.linear.petsc.PetscSolver`): the integrators, the objective,
  Newton's line search and stopping rule run unchanged, the same on every rank;
* :mod:`~fem3d.parallel.run`: the run loop of ``fem3d run`` and ``fem3d resume`` under
  ``mpiexec``: ``energy.csv`` and the one-process ``checkpoint.npz`` (the whole state
  gathered) from rank 0 (resumable on any rank count), frames by
  :mod:`~fem3d.parallel.pieces` (one ``.vtu`` piece per rank, a ``.pvtu`` per frame and a
  ``.pvd``).

docs/parallel.md says what runs, how, and what it measured.
"""

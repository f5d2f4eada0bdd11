"""Parameter sweeps on Dask distributed: ``fem3d sweep SWEEP.toml``.

A sweep file names a base scene and the fields to vary, as dotted key paths of the scene
(``bodies[0].material.E``, ``simulation.dt``); every combination is one *case*: the base
scene with those overrides (:func:`fem3d.scene.load.apply_overrides`), run by the code of
``fem3d run`` (:func:`fem3d.app.run.run_scene`) as one Dask task in a worker process. See
``docs/sweeps.md`` for the file format, the output layout and cluster use.

Stages
------
1. :func:`.spec.load_sweep_file` - TOML -> :class:`.spec.SweepFile` (pydantic; one-line errors that
   name the key path, exit status 2 on the command line).
2. :func:`.plan.expand_cases` - the cases' overrides: the cartesian product of ``[grid]``, the
   rows of ``[zip]``, of ``[sample]`` (seeded random, Latin hypercube, Sobol, Halton) and of
   ``[[cases]]``; each non-empty part is one factor of the product.
3. :func:`.plan.plan_sweep` - resolved scenes and case ids (the first 16 hex digits of the resolved
   scene's :meth:`~fem3d.scene.spec.Scene.digest`), which cases are already complete.
4. :func:`.run.run_sweep` - the Dask part: one task per case to run (embedded ``LocalCluster``
   with single-threaded worker processes, or an existing scheduler), a progress bar, fault
   tolerance (a worker that dies has its case rescheduled elsewhere by the scheduler), then
   ``results.csv`` and ``results.png`` (:mod:`.results`).

``fem3d sweep`` itself (argument parsing) is :mod:`.cli`.

Output folder ``DIR``
---------------------
``DIR/sweep.json`` (the sweep and its case list), ``DIR/results.csv``, ``DIR/results.png``,
and per case ``DIR/cases/<id>/``: ``scene.json`` (the resolved scene), what ``fem3d run``
writes (frames, ``energy.csv``), ``trajectory.npz`` in dataset mode (:mod:`fem3d.io.dataset`),
``started.json`` (which worker, process and attempt) and, written last by an atomic rename,
``summary.json``: a case folder holding ``summary.json`` is complete; any other is partial
and is cleared and run again by the next invocation.
"""

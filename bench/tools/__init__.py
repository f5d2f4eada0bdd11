"""One-off checks and comparisons kept for reuse, not run by ``python -m bench`` or
``bench/all.sh``: each is ``python -m bench.tools.<name>`` (its docstring says what it does).

- :mod:`.contact_check` - every contact gallery scene run for its whole duration, each
  step's state checked (no intersection, no vertex behind a plane, rest).
- :mod:`.pile_check` - the contact pile run to rest through ``fem3d run``, frame by frame.
- :mod:`.path_check` - the contact substeps' straight-motion check timed against an older
  checkout's.
- :mod:`.contact_oldnew` - contact scenes, this tree against an older checkout: speed and how
  far the trajectories part.
"""

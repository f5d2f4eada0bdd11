"""Generated kernels at run time: the back-end choice (:mod:`.backend`), dispatch
(:mod:`.dispatch`) and the race-free thread schedule of the fused C assemblies
(:mod:`.schedule`).
"""

"""Parameter sweeps on Dask."""

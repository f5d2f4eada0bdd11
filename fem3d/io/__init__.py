"""Files: atomic writes and input checks, run folders, frames, the energy log, previews,
checkpoints and datasets."""

"""What users run: the command line, the run loop, the viewer and sweeps."""

"""On-disk formats: atomic writes, sequences, trajectories."""

"""Training runs: the trainer (``Experiment``, P >= 1 members), collection, the
members' checkpoints, the run folder, its logs, thread placement and sweeps."""

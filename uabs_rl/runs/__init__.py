"""Run folders: their layout (``RunFolder``), the checkpoint files, the metrics file,
the folder's lock and identity, and the sweeps that group runs for a report."""

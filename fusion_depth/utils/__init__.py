"""The lowest layer: what every other part uses and that knows nothing of depth or training
(console noise, progress, tables, atomic file writes, checkpoint files read as data)."""

"""Named presets: `tiny` (CPU, minutes) and `paper` (GPU)."""

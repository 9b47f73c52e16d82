"""Inference: `DecomposeConfig`, the fits, sampling, refinement and `decompose`."""

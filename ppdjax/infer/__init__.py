"""Inference: density sampling and refinement through physics, decompose, evaluation."""

"""Evaluation: `decompose`'s stages over a dataset split, the baselines and the rows of the paper's tables."""

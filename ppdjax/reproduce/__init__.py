"""The pipelines that make the shipped models and tables: `python -m ppdjax.reproduce`."""

"""Reports of results: provenance records and the results index."""

"""The 4D chain of subscans, backwards in time: the per-subscan step, detection, lineage, the 4D files."""

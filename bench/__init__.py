"""Benchmarks (``python -m bubsub.bench``)."""

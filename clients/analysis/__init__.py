"""``bubsub analyse``: foam physics from reconstructed meshes (tables, summary, pictures).

The computations live in :mod:`bubsub.core.analysis`; this package reads
reconstruction folders, runs them and writes the results
(:func:`analyse`, :meth:`Analysis.write`). Definitions and measurements:
docs/analysis.md.
"""

from bubsub.clients.analysis.folders import Analysis, analyse, default_contact_gap, read_reconstruction

__all__ = ["Analysis", "analyse", "default_contact_gap", "read_reconstruction"]

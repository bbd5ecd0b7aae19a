"""Foam physics from bubble meshes: shape, contacts, regions (liquid fraction, texture), dynamics.

* :mod:`~bubsub.core.analysis.shape`: volume, area, centroid, equivalent radius, sphericity,
  shape tensor and FoamQuant's internal strain of one closed mesh;
* :mod:`~bubsub.core.analysis.contacts`: closest-surface distances between bubbles, contacts,
  film areas, coordination;
* :mod:`~bubsub.core.analysis.regions`: liquid fraction and texture tensor on a Cartesian grid
  and in cylindrical shells about the rotation axis;
* :mod:`~bubsub.core.analysis.dynamics`: growth rates and the von Neumann-Mullins law, T1
  events, disappearances and coalescences, sizes over time;
* :mod:`~bubsub.core.analysis.snapshot`: all of one foam's tables (:func:`analyse_meshes`).

Definitions: docs/analysis.md.
"""

from bubsub.core.analysis.contacts import Contacts, find_contacts, surface_distance
from bubsub.core.analysis.dynamics import Step, fit_growth_law, growth_rates, size_tables, t1_events, track_events
from bubsub.core.analysis.regions import Domain, texture_summary
from bubsub.core.analysis.shape import bubble_shape, solid_moments, strain_from_axes
from bubsub.core.analysis.snapshot import Snapshot, analyse_meshes

__all__ = ["Contacts", "find_contacts", "surface_distance", "Step", "fit_growth_law", "growth_rates", "size_tables",
           "t1_events", "track_events", "Domain", "texture_summary", "bubble_shape", "solid_moments",
           "strain_from_axes", "Snapshot", "analyse_meshes"]

"""The phases of one reconstruction: preview, initial bubbles, topology, repair, refinement, levels by size."""

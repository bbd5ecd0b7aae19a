"""Checks before any work (settings, bubble signal, impossible data, the detector's sides) and the field of view."""

"""Simulated scans on disk, reconstructions scored against them, the voxel baseline of --holdout and 4D."""

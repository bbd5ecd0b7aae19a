"""The reconstruction pipeline: the commands' drivers here, their stages in inputs/, static/, regions/,
dynamic4d/ and results/, simulation and scoring in evaluation/."""

"""Training a map-conditioned policy on map-table data sets, and its open-loop evaluations (collisions, coverage, timing)."""

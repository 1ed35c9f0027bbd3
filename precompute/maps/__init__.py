"""Per-map tables for map-conditioned policies: the worlds a farm draws from, the farm, and the map-table data set."""

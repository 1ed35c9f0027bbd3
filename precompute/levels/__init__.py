"""Level sets: from a start, on a grid, optionally safe in a local map (viability)."""

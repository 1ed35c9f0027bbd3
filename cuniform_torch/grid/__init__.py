"""Grids of a state space: integer cells, packed int64 keys, sorted-key and hashed lookups."""

"""Distilling a table set into one start-conditioned MLP, and evaluating it at held-out starts."""

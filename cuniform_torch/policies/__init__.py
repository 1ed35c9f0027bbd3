"""Policies pi(u | x, t): the table policy, table sets, the distilled MLP, the start-conditioned MLP and their checkpoint file."""

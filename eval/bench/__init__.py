"""Speed benchmarks: per-command time of the controllers against pytorch_mppi, max-flow solvers, the proposal bank soak."""

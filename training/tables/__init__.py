"""Distilling one table into an MLP: training points, the epoch loop, the training state, evaluation and figures."""

"""Distillation of C-Uniform tables into small MLP policies.

* ``python -m training.distill --tables out/dubins.npz``: the training script (:mod:`training.distill`), one
  table (or several pooled) -> pi(u | x, t); ``--tables DIR`` of a table set (:mod:`training.sets.distill`) ->
  one start-conditioned pi(u | x, t, x0);
* :mod:`training.tables.evaluate`: the comparison of a policy (a distilled MLP, or anything with the Policy interface)
  with its table: KL per level at cell centres and jittered points, coverage of real rollouts, fallback rates
  and sizes. The script calls it at the end; it works the same on a saved checkpoint;
* ``python -m training.sets.evaluate``: a start-conditioned MLP against its set at held-out starts, and the
  controller's command time with each;
* helpers: :mod:`training.tables.samples` (the training points and weights), :mod:`training.tables.train_state` (``--resume``),
  :mod:`training.tables.figures` (TensorBoard figures), :mod:`training.tables.support` (the cells a checkpoint records).
"""

from precompute.startup import install_when_run_as_command

install_when_run_as_command()  # python -m ...: Ctrl-C during the imports is one line and exit 130

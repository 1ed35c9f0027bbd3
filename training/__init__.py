"""Distillation of a C-Uniform table into a small MLP policy.

* ``python -m training.distill --tables out/dubins.npz``: the training script (:mod:`training.distill`);
* :mod:`training.evaluate`: the comparison of a policy (a distilled MLP, or anything with the Policy interface)
  with its table: KL per level at cell centres and jittered points, coverage of real rollouts, fallback rates
  and sizes. The script calls it at the end; it works the same on a saved checkpoint.
"""

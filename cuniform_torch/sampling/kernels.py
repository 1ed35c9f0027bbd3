"""A compiled CPU loop (numba) for the last step of a start-relative rollout: origin-frame states to the world.

Shapes: N samples, T horizon, d >= 3 state dimensions.

:func:`~cuniform_torch.sampling.rollout.rollout` of a table or MLP from a pose rolls out at the origin and then moves the
``[N, T+1, d]`` states to the pose (:func:`~cuniform_torch.common.frames.se2_to_world`). In torch that is about ten
passes over strided views: 1.3 ms at N = 10000, T = 15 on one core of the development machine, against
0.24 ms here. This loop reads the time-major stack of the column-major step outputs (``[T+1, d, N]``, every row
contiguous) once and writes the world states ``[N, T+1, d]`` once, with the arithmetic of ``se2_to_world`` in
the states' dtype: ``x = (px + lx c) - ly s``, ``y = (py + lx s) + ly c``, heading ``wrap(lth + ptheta)`` with
``wrap(a) = ((a + pi) mod 2 pi) - pi`` (mod as torch's ``remainder``: the sign of the divisor); the further
dimensions are copied. Headings come out bit-identical to the torch path; x and y agree to an ulp or so
(torch's ``addcmul`` may fuse the multiply-add, and its cos and sin may round differently).

One pose ``[d]`` or one per robot (``[B, d]``, or the ``[N, d]`` start rows of a batch, robot-major): the cos and
sin of each pose are one scalar libm call inside the loop, so a robot's world states are the same bits whether
it is rolled out alone or in a batch of B, whatever a vectorized cos would do with a pose's position in a vector
(torch's CPU cos happens to be position-independent on the development machine; nothing promises it).

numba is imported lazily (:func:`~cuniform_torch.tables.cpu_kernels.available` says whether it can be used); the first
call compiles the loop (cached on disk when the directory is writable). Without numba, or off the CPU, the
rollout uses the torch path.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.tables import cpu_kernels

__all__ = ["usable", "to_world", "to_world_time_major"]


@functools.cache
def _kernel():
    from cuniform_torch.sampling import frame_loops  # imports numba: only when a loop is used

    return frame_loops.to_world, frame_loops.to_world_time_major, frame_loops.pose_runs


def usable(x: Tensor) -> bool:
    """Whether :func:`to_world` serves states like ``x`` (a CPU float32 or float64 tensor, numba installed)."""
    return x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64) and cpu_kernels.available()


def to_world(local: Tensor, pose: Tensor) -> Tensor:
    """``local [T+1, d, N]`` (origin frame; any strides: a time-major stack, or ``[N, T+1, d]`` states viewed
    with ``permute(1, 2, 0)``) moved to ``pose [d]``, or sample ``i`` to ``pose[i // (N / P)]`` of ``pose [P, d]``
    (P dividing N: a batch's per-robot poses ``[B, d]``, or its per-sample starts ``[N, d]``): ``[N, T+1, d]``
    contiguous."""
    steps, d, n = local.shape
    out = torch.empty((n, steps, d), dtype=local.dtype, device=local.device)
    _kernel()[0](local.numpy(), *_pose_args(local, pose), out.numpy())
    return out


def to_world_time_major(local: Tensor, pose: Tensor) -> Tensor:
    """``local [T+1, d, N]`` (origin frame, contiguous: a rollout's time-major states) moved to ``pose [d]`` (or
    per-sample poses ``[P, d]`` as in :func:`to_world`): ``[T+1, d, N]`` contiguous, the values of
    :func:`to_world` (``to_world(local, pose)`` equals this ``.permute(2, 0, 1)``)."""
    out = torch.empty_like(local, memory_format=torch.contiguous_format)
    _kernel()[1](local.numpy(), *_pose_args(local, pose), out.numpy())
    return out


def _pose_args(local: Tensor, pose: Tensor) -> tuple:
    """The kernels' arguments for ``pose [d]`` or ``[P, d]``: the runs of equal consecutive poses ``[R, 3]``, their
    cos and sin ``[R]`` (one scalar libm call per run inside a compiled loop: a pose's values are the same for any
    P), their samples' bounds ``[R+1]``, ``pi, 2 pi``; reals in the dtype of ``local``."""
    n = local.shape[2]
    poses = pose.detach().reshape(-1, pose.shape[-1]).to(local.dtype).numpy()  # [P, d]
    p = poses.shape[0]
    if n % p:
        raise ValueError(f"{p} poses for {n} samples: the number of poses must divide the samples (sample i "
                         f"belongs to pose i // (N / P))")
    runs, c, s = np.empty((p, 3), poses.dtype), np.empty(p, poses.dtype), np.empty(p, poses.dtype)
    bounds = np.empty(p + 1, np.int64)
    r = _kernel()[2](poses, n // p, runs, c, s, bounds)
    real = poses.dtype.type
    return runs[:r], c[:r], s[:r], bounds[:r + 1], real(math.pi), real(2 * math.pi)

"""A map policy's rollout on a CPU with its per-step work in one compiled loop (numba): the fused path of
:meth:`MapPolicy.fused_rollout <cuniform_torch.maps.policy.MapPolicy.fused_rollout>`.

Shapes: N samples, T horizon, A actions, Hd hidden units, F inputs of the first layer (x, y, cos, sin, then
P probes x C local features), C x H x W the local feature map.

A rollout of the map policy through :func:`~cuniform_torch.sampling.rollout.rollout` is T steps of
``action_probs`` (features, local-feature probes, the MLP, softmax, the support check and its counters), an
inverse-CDF draw and the :class:`~cuniform_torch.systems.models.Dubins` step: some 40 small tensor ops a step,
each paying a dispatch of a few microseconds, so that at N = 32 the rollout cost 6.8 ms where its arithmetic is a
few hundred microseconds. Here each step is the MLP's matrix products in torch (``addmm`` into preallocated
buffers: BLAS is what they need) and one compiled loop over the states for everything else: the softmax draw of
step t, the Dubins step, then the next state's features, its local-feature probes (bilinear, as ``grid_sample``
with ``align_corners=False`` and zero padding reads them) and its support check.

It draws what the step-by-step path draws: the uniforms of all T steps come from one ``torch.rand((T, N))`` on
the rollout's generator, which on a CPU is the same stream as T calls of ``torch.rand((N, 1))``; the draw picks
the first action whose cumulative probability exceeds ``u`` times the row's total, as
:func:`~cuniform_torch.policies.mlp_ops.inverse_cdf_draw` does, and the Dubins step is
:meth:`Dubins.step <cuniform_torch.systems.models.Dubins.step>`'s arithmetic in float32. The two paths agree to
float rounding (cos, sin and exp of a compiled loop may differ by an ulp from torch's vectorized ones), so a
draw can differ only when a uniform falls within that rounding of a cumulative probability.

numba is imported lazily; the first call compiles the loops (cached on disk when the directory is writable).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch import Tensor

from cuniform_torch.tables import cpu_kernels

__all__ = ["usable", "warm_up", "rollout_start_frame"]


@functools.cache
def _kernels():
    from cuniform_torch.maps import rollout_loops  # imports numba: only when a loop is used

    return rollout_loops.features, rollout_loops.draw_step_features


def usable(device: torch.device, dtype: torch.dtype) -> bool:
    """Whether the compiled rollout serves a policy (and its starts) on ``device`` in ``dtype``: a CPU, float32,
    numba installed."""
    return torch.device(device).type == "cpu" and dtype == torch.float32 and cpu_kernels.available()


@functools.cache
def warm_up() -> None:
    """Compile (or load from numba's disk cache) the loops now, with a 2-state rollout: a controller calls this when
    it is made, so that no control cycle pays for the compilation (seconds)."""
    from cuniform_torch.sampling import kernels as frame_kernels

    layers = [(torch.zeros((2, 2)), torch.zeros(2)), (torch.zeros((2, 3)), torch.zeros(3))]
    geometry = dict(dt=0.1, speed=1.0, origin_x=-1.0, origin_y=-1.0, resolution=0.5, half_x=1.0, half_y=1.0,
                    cell_x=0.1, cell_y=0.1)
    states, _, _, _ = rollout_start_frame(torch.zeros((2, 2)), torch.zeros((5, 2)), layers, torch.zeros((3, 1)),
                                          torch.zeros((1, 1, 4, 4)), torch.zeros((1, 2)), geometry, 2, 1, None)
    frame_kernels.to_world_time_major(states, torch.tensor([0.5, 0.5, 0.1]))


def rollout_start_frame(map_bias: Tensor, w_state: Tensor, layers: list[tuple[Tensor, Tensor]], actions: Tensor,
                        local_map: Tensor | None, probes: Tensor, geometry: dict[str, float], num_samples: int,
                        horizon: int, generator: torch.Generator | None,
                        uniforms: Tensor | None = None) -> tuple[Tensor, Tensor, int, int]:
    """``num_samples`` rollouts of ``horizon`` steps from the origin of the start frame (a Dubins car, see the
    module docstring): states ``[T+1, 3, N]`` (time-major), actions ``[N, T, q]``, and the near and miss counts.

    ``map_bias [T+1, Hd]``, ``w_state [F, Hd]``, ``layers`` (``(weight^T, bias)`` of the body) are the folded
    network of the map last set; ``local_map [1, C, H, W]`` or None; ``probes [P, 2]``; ``geometry``: ``dt``,
    ``speed``, the patch ``origin_x``, ``origin_y``, ``resolution`` and the support box ``half_x``, ``half_y``,
    ``cell_x``, ``cell_y``."""
    features, draw_step_features = _kernels()
    n, hd, n_actions = num_samples, w_state.shape[1], actions.shape[0]
    if uniforms is None:
        uniforms = torch.rand((horizon, n), generator=generator, dtype=torch.float32)  # [T, N]
    uniforms = uniforms.contiguous()
    states = torch.zeros((horizon + 1, 3, n), dtype=torch.float32)
    picks = torch.empty((horizon, n), dtype=torch.int64)
    feat = torch.empty((n, w_state.shape[0]), dtype=torch.float32)
    ok = torch.empty(n, dtype=torch.bool)
    hidden = [torch.empty((n, hd)), torch.empty((n, hd))]
    logits = torch.empty((n, n_actions))
    counts = np.zeros(2, dtype=np.int64)
    fmap = (local_map[0] if local_map is not None else torch.zeros((0, 1, 1))).contiguous().numpy()
    geo = np.array([geometry[k] for k in ("dt", "speed", "origin_x", "origin_y", "resolution", "half_x", "half_y",
                                          "cell_x", "cell_y")], dtype=np.float32)
    probes_np = probes.to(torch.float32).contiguous().numpy()
    states_np, feat_np, ok_np, logits_np = states.numpy(), feat.numpy(), ok.numpy(), logits.numpy()
    uniforms_np, picks_np = uniforms.numpy(), picks.numpy()
    actions_np = actions[:, 0].to(torch.float32).contiguous().numpy()
    pi, two_pi = np.float32(math.pi), np.float32(2.0 * math.pi)
    silu = torch.nn.functional.silu
    features(0, states_np, feat_np, ok_np, counts, fmap, probes_np, geo)
    for t in range(horizon):
        h = torch.addmm(map_bias[t], feat, w_state, out=hidden[0])  # [N, Hd]
        for k, (weight, bias) in enumerate(layers):
            target = logits if k == len(layers) - 1 else hidden[(k + 1) % 2]
            h = torch.addmm(bias, silu(h, inplace=True), weight, out=target)
        # step t's draw and Dubins step, then step t + 1's features: one compiled call
        draw_step_features(t, logits_np, uniforms_np, states_np, picks_np, actions_np, ok_np, geo, pi, two_pi,
                           feat_np, counts, fmap, probes_np)
    taken = actions.index_select(0, picks.T.reshape(-1)).view(n, horizon, actions.shape[1])  # [N, T, q]
    return states, taken, int(counts[0]), int(counts[1])

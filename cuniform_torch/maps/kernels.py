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

__all__ = ["usable", "rollout_start_frame"]


@functools.cache
def _kernels():
    import numba

    @numba.njit(cache=True, nogil=True, inline="always")
    def read(fmap, c, ix, iy):
        """Bilinear read of channel ``c`` at pixel coordinates ``(ix, iy)`` (column, row); zero off the map."""
        H, W = fmap.shape[1], fmap.shape[2]
        x0f, y0f = math.floor(ix), math.floor(iy)
        wx, wy = ix - x0f, iy - y0f
        x0, y0 = int(x0f), int(y0f)
        v = np.float32(0.0)
        for dy in range(2):
            yy = y0 + dy
            if yy < 0 or yy >= H:
                continue
            fy = wy if dy else np.float32(1.0) - wy
            for dx in range(2):
                xx = x0 + dx
                if 0 <= xx < W:
                    v += (wx if dx else np.float32(1.0) - wx) * fy * fmap[c, yy, xx]
        return v

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def features(t, states, feat, ok, counts, fmap, probes, geo):
        """The first layer's inputs of the states at step ``t`` (``states [T+1, 3, N]``) into ``feat [N, F]``,
        ``ok [N]`` (inside the support box and finite) and the near / miss counters ``counts [2]``."""
        n_states = states.shape[2]
        channels = fmap.shape[0]
        ox, oy, res, half_x, half_y, cell_x, cell_y = geo[2], geo[3], geo[4], geo[5], geo[6], geo[7], geo[8]
        for i in range(n_states):
            x, y, th = states[t, 0, i], states[t, 1, i], states[t, 2, i]
            c, s = np.float32(math.cos(th)), np.float32(math.sin(th))
            feat[i, 0], feat[i, 1], feat[i, 2], feat[i, 3] = x, y, c, s
            excess = max((abs(x) - half_x) / cell_x, (abs(y) - half_y) / cell_y)
            finite = math.isfinite(x) and math.isfinite(y) and math.isfinite(th)
            miss = not finite or not excess <= 1.0
            ok[i] = not miss
            if miss:
                counts[1] += 1
            elif excess > 0.0:
                counts[0] += 1
            k = 4
            for p in range(probes.shape[0]):
                ahead, left = probes[p, 0], probes[p, 1]
                px = (x + c * ahead) - s * left
                py = (y + s * ahead) + c * left
                ix = (px - ox) / res - np.float32(0.5)
                iy = (py - oy) / res - np.float32(0.5)
                for ch in range(channels):
                    feat[i, k] = read(fmap, ch, ix, iy) if finite else np.float32(0.0)
                    k += 1

    @numba.njit(cache=True, nogil=True, boundscheck=False)
    def draw_and_step(t, logits, uniforms, states, picks, actions, ok, geo, pi, two_pi):
        """Step ``t``'s draw from ``logits [N, A]`` (uniform where not ``ok``) with ``uniforms[t]``, into
        ``picks [T, N]``, and the Dubins step of ``states[t]`` into ``states[t + 1]``."""
        n_actions = logits.shape[1]
        dt, speed = geo[0], geo[1]
        for i in range(logits.shape[0]):
            if ok[i]:
                top = logits[i, 0]
                for a in range(1, n_actions):
                    top = max(top, logits[i, a])
                total = np.float32(0.0)
                for a in range(n_actions):
                    total += np.float32(math.exp(logits[i, a] - top))
                target = uniforms[t, i] * total
                cdf = np.float32(0.0)
                pick = n_actions - 1
                for a in range(n_actions):
                    cdf += np.float32(math.exp(logits[i, a] - top))
                    if cdf > target:
                        pick = a
                        break
            else:
                pick = min(int(uniforms[t, i] * n_actions), n_actions - 1)
            picks[t, i] = pick
            a_val = actions[pick] * dt + states[t, 2, i] + pi
            m = np.fmod(a_val, two_pi)
            if m < 0:
                m += two_pi
            th = m - pi
            states[t + 1, 2, i] = th
            states[t + 1, 0, i] = states[t, 0, i] + (np.float32(math.cos(th)) * speed) * dt
            states[t + 1, 1, i] = states[t, 1, i] + (np.float32(math.sin(th)) * speed) * dt

    return features, draw_and_step


def usable(x0: Tensor, dtype: torch.dtype) -> bool:
    """Whether the compiled rollout serves a start like ``x0`` for a policy of ``dtype`` (a CPU float32 start and
    policy, numba installed)."""
    return (x0.device.type == "cpu" and x0.dtype == torch.float32 and dtype == torch.float32
            and cpu_kernels.available())


def rollout_start_frame(map_bias: Tensor, w_state: Tensor, layers: list[tuple[Tensor, Tensor]], actions: Tensor,
                        local_map: Tensor | None, probes: Tensor, geometry: dict[str, float], num_samples: int,
                        horizon: int, generator: torch.Generator | None) -> tuple[Tensor, Tensor, int, int]:
    """``num_samples`` rollouts of ``horizon`` steps from the origin of the start frame (a Dubins car, see the
    module docstring): states ``[T+1, 3, N]`` (time-major), actions ``[N, T, q]``, and the near and miss counts.

    ``map_bias [T+1, Hd]``, ``w_state [F, Hd]``, ``layers`` (``(weight^T, bias)`` of the body) are the folded
    network of the map last set; ``local_map [1, C, H, W]`` or None; ``probes [P, 2]``; ``geometry``: ``dt``,
    ``speed``, the patch ``origin_x``, ``origin_y``, ``resolution`` and the support box ``half_x``, ``half_y``,
    ``cell_x``, ``cell_y``."""
    features, draw_and_step = _kernels()
    n, hd, n_actions = num_samples, w_state.shape[1], actions.shape[0]
    uniforms = torch.rand((horizon, n), generator=generator, dtype=torch.float32)  # [T, N]
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
    for t in range(horizon):
        features(t, states_np, feat_np, ok_np, counts, fmap, probes_np, geo)
        h = torch.addmm(map_bias[t], feat, w_state, out=hidden[0])  # [N, Hd]
        for k, (weight, bias) in enumerate(layers):
            target = logits if k == len(layers) - 1 else hidden[(k + 1) % 2]
            h = torch.addmm(bias, silu(h, inplace=True), weight, out=target)
        draw_and_step(t, logits_np, uniforms_np, states_np, picks_np, actions_np, ok_np, geo, pi, two_pi)
    taken = actions.index_select(0, picks.T.reshape(-1)).view(n, horizon, actions.shape[1])  # [N, T, q]
    return states, taken, int(counts[0]), int(counts[1])

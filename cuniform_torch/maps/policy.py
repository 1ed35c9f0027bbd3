"""The map-conditioned policy pi(u | x, t, local map) of C-Free-Uniform (arXiv 2510.16905).

Shapes: N states, d state dimensions, F state features, E map embedding, Hd hidden units, A actions, H x W patch.

:class:`MapPolicy` is a :class:`~cuniform_torch.maps.encoder.MapEncoder` over the robot-frame occupancy patch
(computed *once* per map: :meth:`MapPolicy.set_map`) and an MLP over the state / time features of
:class:`~cuniform_torch.policies.mlp.MLPPolicy` (``x_i / scale_i`` per non-periodic dimension, ``cos``, ``sin`` per angle,
``t / T``) together with that embedding. The first layer is split, ``W_x f + W_e e + b``, so ``W_e e + b`` is
computed with the embedding and a lookup costs what an MLPPolicy's does. It answers ``action_probs(x, t)``
and ``sample(x, t, generator)`` for the map last set, so it drops into :func:`~cuniform_torch.sampling.rollout.rollout`
and every controller (:class:`~cuniform_torch.controllers.cfu.CFUMPPI` sets the map each command).

With ``local_features = C > 0`` (:mod:`~cuniform_torch.maps.local_features`) the first layer also reads ``P * C`` features
sampled bilinearly from a stride-1 feature map of the patch at the state and at probe points ahead of it:
``W_x f + W_e e + W_l l(x) + b``. The feature map is computed once per map too (``set_map``); ``C = 0`` (the
default, and what a checkpoint without the key means) is the map-embedding-only network, unchanged.

States are in the start pose's frame (``start_relative`` on an SE(2)-invariant system), like the patch.
Support: the box of the training cells, as an MLPPolicy without ``support``: each non-periodic dimension
within ``feature_scale_i + cell_size_i / 2`` of 0 is answered by the network; within one more cell too, counted
in ``nearest_hits``; beyond, or NaN / infinite, the uniform row, counted in ``misses``. The safe cells differ
from map to map, so no per-cell support is kept.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from cuniform_torch.common.checks import check_positive_int
from cuniform_torch.grid.cells import Grid
from cuniform_torch.maps import kernels
from cuniform_torch.maps.encoder import MapEncoder, PatchSpec
from cuniform_torch.maps.local_features import PROBES, LocalFeatures
from cuniform_torch.policies.mlp_ops import check_query, inverse_cdf_draw, inverse_cdf_pick, state_features
from cuniform_torch.sampling.fallback_counts import CountsFallbacks, FallbackCounts
from cuniform_torch.sampling.start_watch import StartWatch, WatchesStart
from cuniform_torch.systems import MAX_ACTIONS, MAX_HORIZON, System
from cuniform_torch.systems.models import Dubins

__all__ = ["MapPolicyConfig", "MapPolicy", "MAX_MAP_HIDDEN", "MAX_MAP_LAYERS", "MAX_MAP_CHANNELS",
           "MAX_MAP_PARAMETERS", "MAX_MAP_ACTIVATIONS"]

# Limits of a config, checked when it is made (MapPolicyConfig.__post_init__): before any network is built, so a
# checkpoint's config cannot make the reader allocate more than these describe (see docs/formats.md).
MAX_MAP_HIDDEN = 4096
"""the most hidden units (``hidden``) and embedding size (``embed``)"""
MAX_MAP_LAYERS = 16
"""the most hidden layers"""
MAX_MAP_CHANNELS = 256
"""the most encoder channels (``channels``) and local feature channels (``local_features``)"""
MAX_MAP_PARAMETERS = 1 << 26
"""the most parameters in all (:attr:`MapPolicyConfig.num_parameters`; 67M, 256 MiB of float32)"""
MAX_MAP_ACTIVATIONS = 1 << 26
"""the most values of one map's largest feature map (:attr:`MapPolicyConfig.map_activations`), which
``set_map`` computes"""
_MAX_STATE_DIM = 64


@dataclass
class MapPolicyConfig:
    """Sizes, input features and patch spec of a :class:`MapPolicy` (stored in the checkpoint as a dict)."""

    state_dim: int
    num_actions: int
    horizon: int
    periodic: list[bool]
    feature_scale: list[float]
    """divisor of each non-periodic dimension (ignored on angle dimensions)"""
    patch: dict[str, Any]
    """the :class:`PatchSpec` as a dict (shape, resolution, origin)"""
    hidden: int = 128
    layers: int = 2
    embed: int = 32
    """map embedding size E"""
    channels: int = 8
    """the encoder's base channel count c"""
    local_features: int = 0
    """channels C of the local feature map sampled at each state's probes (0: none, the original network)"""

    def __post_init__(self) -> None:
        for name in ("state_dim", "num_actions", "horizon", "hidden", "layers", "embed", "channels"):
            check_positive_int(f"MapPolicyConfig.{name}", getattr(self, name), integral=False)
        if max(self.hidden, self.embed) > MAX_MAP_HIDDEN or self.layers > MAX_MAP_LAYERS \
                or self.channels > MAX_MAP_CHANNELS:
            raise ValueError(f"MapPolicyConfig: at most {MAX_MAP_LAYERS} layers, {MAX_MAP_HIDDEN} hidden units or "
                             f"embedding and {MAX_MAP_CHANNELS} channels, got layers {self.layers}, hidden "
                             f"{self.hidden}, embed {self.embed}, channels {self.channels}")
        for name, limit in (("state_dim", _MAX_STATE_DIM), ("num_actions", MAX_ACTIONS), ("horizon", MAX_HORIZON)):
            if getattr(self, name) > limit:
                raise ValueError(f"MapPolicyConfig.{name} is {getattr(self, name)}; at most {limit} is supported")
        if not isinstance(self.periodic, (list, tuple)) or not all(isinstance(p, bool) for p in self.periodic):
            raise ValueError(f"MapPolicyConfig: periodic must be a list of bools, got {self.periodic!r}")
        if not isinstance(self.feature_scale, (list, tuple)) or len(self.periodic) != self.state_dim \
                or len(self.feature_scale) != self.state_dim:
            raise ValueError(f"MapPolicyConfig: periodic and feature_scale need {self.state_dim} entries each")
        if any(isinstance(s, bool) or not isinstance(s, (int, float)) or not (0 < s < math.inf)
               for s in self.feature_scale):
            raise ValueError(f"MapPolicyConfig: feature_scale must be positive finite numbers, got {self.feature_scale}")
        lf = self.local_features
        if isinstance(lf, bool) or not isinstance(lf, int) or not 0 <= lf <= MAX_MAP_CHANNELS:
            raise ValueError(f"MapPolicyConfig.local_features must be an integer in 0..{MAX_MAP_CHANNELS}, got {lf!r}")
        if lf and list(self.periodic[:3]) != [False, False, True]:
            raise ValueError(f"MapPolicyConfig: local_features need states (x, y, heading, ...), but periodic is "
                             f"{self.periodic}")
        self.patch = PatchSpec.from_dict(self.patch).to_dict()  # checked, normalised
        # the one check of the network's size and of a map's feature maps, before anything is allocated
        if self.num_parameters > MAX_MAP_PARAMETERS:
            raise ValueError(f"MapPolicyConfig: hidden {self.hidden} x layers {self.layers}, embed {self.embed}, "
                             f"channels {self.channels}, local_features {lf} on a {self.patch['shape']} patch make "
                             f"{self.num_parameters} parameters; at most {MAX_MAP_PARAMETERS} are supported")
        if self.map_activations > MAX_MAP_ACTIVATIONS:
            raise ValueError(f"MapPolicyConfig: channels {self.channels} and local_features {lf} on a "
                             f"{self.patch['shape']} patch make feature maps of {self.map_activations} values per "
                             f"map; at most {MAX_MAP_ACTIVATIONS} are supported")

    @property
    def patch_spec(self) -> PatchSpec:
        return PatchSpec.from_dict(self.patch)

    @property
    def num_features(self) -> int:
        return sum(2 if p else 1 for p in self.periodic) + 1

    @property
    def num_parameters(self) -> int:
        """Parameters of the :class:`MapPolicy` this config describes (counted from the sizes: nothing is built)."""
        c, E, Hd, A, C = self.channels, self.embed, self.hidden, self.num_actions, self.local_features
        h, w = self.patch["shape"]
        for _ in range(3):  # MapEncoder: three stride-2, padding-1 3x3 convolutions
            h, w = (h - 1) // 2 + 1, (w - 1) // 2 + 1
        encoder = (9 * c + c) + (9 * c * 2 * c + 2 * c) + (9 * 2 * c * 2 * c + 2 * c) + (2 * c * h * w + 1) * E
        mlp = (self.num_features + 1) * Hd + E * Hd + (self.layers - 1) * (Hd + 1) * Hd + (Hd + 1) * A
        local = (9 * C + 18 * C * C + len(PROBES) * C * Hd) if C else 0  # LocalFeatures (no biases) and inp_l
        return encoder + mlp + local

    @property
    def map_activations(self) -> int:
        """Values of the largest feature map ``set_map`` computes for one map: the encoder's first convolution
        (``channels`` at half resolution) or the local feature map (``local_features`` at full resolution)."""
        H, W = self.patch["shape"]
        return max(self.channels * ((H - 1) // 2 + 1) * ((W - 1) // 2 + 1), self.local_features * H * W)

    def to_dict(self) -> dict[str, Any]:
        """The checkpoint's ``config``; ``local_features`` only when > 0, so a C = 0 checkpoint is the old one."""
        out = dataclasses.asdict(self)
        if not out["local_features"]:
            del out["local_features"]
        return out


class MapPolicy(WatchesStart, CountsFallbacks, nn.Module):
    """pi(u | x, t, map): ``set_map(patch)`` once, then ``action_probs(x [N, d], t) -> [N, A]`` for that map.

    ``encode(occupancy [B, H, W]) -> [B, E]``, ``encode_local(occupancy) -> [B, C, H, W]`` (local features only)
    and ``logits(x, t, embedding, local_map, which)`` are the training path (one embedding per state, ``[N, E]``;
    row n reads ``local_map[which[n]]``); ``encodes`` counts the maps encoded by :meth:`set_map`.
    """

    # declared so that nn.Module's __getattr__ (Tensor | Module) does not hide their types
    config: MapPolicyConfig
    actions: Tensor
    inv_scale: Tensor
    _linear_index: Tensor
    _angle_index: Tensor
    _box_half: Tensor
    _box_cell: Tensor
    _uniform: Tensor

    def __init__(self, config: MapPolicyConfig, system: System, actions: Tensor):
        super().__init__()
        if not isinstance(actions, Tensor) or actions.ndim != 2 or actions.shape[0] != config.num_actions:
            raise ValueError(f"actions must be [{config.num_actions}, q], got {list(getattr(actions, 'shape', []))}")
        if list(system.periodic) != list(config.periodic):
            raise ValueError(f"system {system.name} has periodic {list(system.periodic)}, config says {config.periodic}")
        self.config, self.system, self.horizon = config, system, config.horizon
        self.patch_spec = config.patch_spec
        self.register_buffer("actions", actions.detach().clone().float())  # [A, q]
        self.register_buffer("inv_scale", 1.0 / torch.tensor(config.feature_scale, dtype=torch.float32))  # [d]
        self._angle = [i for i, p in enumerate(config.periodic) if p]
        self._linear = [i for i, p in enumerate(config.periodic) if not p]
        self.encoder = MapEncoder(self.patch_spec.shape, config.embed, config.channels)
        self.inp_x = nn.Linear(config.num_features, config.hidden)
        self.inp_e = nn.Linear(config.embed, config.hidden, bias=False)
        body: list[nn.Module] = []
        for _ in range(config.layers - 1):
            body += [nn.SiLU(), nn.Linear(config.hidden, config.hidden)]
        body += [nn.SiLU(), nn.Linear(config.hidden, config.num_actions)]
        self.body = nn.Sequential(*body)
        # built after the rest, so C = 0 draws the same initial weights as before the option existed
        self.local = LocalFeatures(self.patch_spec, config.local_features) if config.local_features else None
        self.inp_l = (nn.Linear(self.local.num_outputs, config.hidden, bias=False) if self.local is not None
                      else None)
        grid = Grid.of(system)
        half = torch.tensor([s + c / 2 for s, c in zip(config.feature_scale, grid.cell_size)])
        # the dimensions as index tensors on the policy's device: a list index would copy from the host every lookup
        # (a wait on a GPU, and no CUDA graph could hold the command)
        self.register_buffer("_linear_index", torch.tensor(self._linear, dtype=torch.long), persistent=False)
        self.register_buffer("_angle_index", torch.tensor(self._angle, dtype=torch.long), persistent=False)
        self.register_buffer("_box_half", half[self._linear], persistent=False)  # [d_lin]
        self.register_buffer("_box_cell", torch.tensor(grid.cell_size)[self._linear], persistent=False)
        self._box_floats = (self._box_half.tolist(), self._box_cell.tolist())
        """the support box as Python floats (float32 values), for the compiled rollout: no host read per command"""
        self.counts = FallbackCounts(self.device)
        """the lookups' fallback counts (:class:`~cuniform_torch.sampling.fallback_counts.FallbackCounts`)"""
        self._start_watch = StartWatch(f"map policy ({system.name})", system, counts=self.counts)
        self.register_buffer("_uniform", torch.full((1, config.num_actions), 1.0 / config.num_actions), persistent=False)
        self._map_bias: Tensor | None = None  # [B, T+1, Hd] per map and level, for the maps last set (set_maps)
        self._w_state: Tensor | None = None  # [F-1 (+ P * C), Hd]
        self._local_map: Tensor | None = None  # [B, C, H, W] for the maps last set (local features only)
        self._layers: list[tuple[Tensor, Tensor]] = []  # the body's (weight^T, bias)
        self._folded: tuple[tuple, tuple[Tensor, Tensor, list[tuple[Tensor, Tensor]]]] | None = None
        """the weights' part of ``set_maps`` and the parameters' identities it was made from"""
        self.encodes = 0
        self.compiled = True
        """roll out through :meth:`fused_rollout` where it applies (False: always step by step)"""

    # -------------------------------------------------------------------------------- traits
    @property
    def device(self) -> torch.device:
        return self.actions.device

    @property
    def dtype(self) -> torch.dtype:
        return self.actions.dtype

    @property
    def start_relative(self) -> bool:
        """True on an SE(2)-invariant system: states and patch are in the start pose's frame."""
        return bool(self.system.se2_invariant)

    @property
    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    # -------------------------------------------------------------------------------- the network
    def features(self, x: Tensor, t: int | Tensor) -> Tensor:
        """``x [N, d]``, ``t`` (int or ``[N]``) -> ``[N, F]`` (MLPPolicy's features)."""
        return state_features(x.to(self.dtype), t, self._linear, self._angle, self.inv_scale, self.config.horizon)

    def encode(self, occupancy: Tensor) -> Tensor:
        """``[B, H, W]`` (bool or 0 / 1) -> ``[B, E]`` map embeddings."""
        return self.encoder(occupancy.to(self.dtype))

    def encode_local(self, occupancy: Tensor) -> Tensor:
        """``[B, H, W]`` (bool or 0 / 1) -> ``[B, C, H, W]`` local feature maps (``local_features > 0`` only)."""
        if self.local is None:
            raise ValueError("this policy has no local features (local_features = 0)")
        return self.local(occupancy.to(self.dtype))

    def logits(self, x: Tensor, t: int | Tensor, embedding: Tensor, local_map: Tensor | None = None,
               which: Tensor | None = None) -> Tensor:
        """``x [N, d]``, ``t``, ``embedding [N, E]`` (or ``[1, E]``) -> logits ``[N, A]`` (differentiable). With
        local features, ``local_map [U, C, H, W]`` (:meth:`encode_local`) and ``which [N]`` (the map of each row;
        None when U = 1) are required."""
        h = self.inp_x(self.features(x, t)) + self.inp_e(embedding)
        if self.local is not None:
            if local_map is None:
                raise ValueError("a policy with local features needs local_map (encode_local of the patches)")
            assert self.inp_l is not None  # built with self.local
            h = h + self.inp_l(self.local.sample(local_map, x.to(self.dtype), which))
        return self.body(h)

    def forward(self, x: Tensor, t: int | Tensor, embedding: Tensor, local_map: Tensor | None = None,
                which: Tensor | None = None) -> Tensor:
        return self.logits(x, t, embedding, local_map, which)

    # -------------------------------------------------------------------------------- one map, many lookups
    def set_map(self, patch: object) -> None:
        """Encode ``patch`` (a robot-frame OccupancyGrid of this policy's :class:`PatchSpec`, on its device) once;
        every lookup until the next call is for that map (and these weights: call it again after training).
        ValueError naming a wrong shape, resolution or origin."""
        occupied = self.patch_spec.check(patch)
        if occupied.device != self.device:
            raise ValueError(f"the patch is on {occupied.device} but the policy is on {self.device}")
        self.set_maps(occupied.unsqueeze(0))

    def set_maps(self, occupied: Tensor) -> None:
        """Encode B robot-frame patches at once (``occupied [B, H, W]``, bool or 0 / 1, this policy's patch shape,
        on its device: what :func:`~cuniform_torch.maps.sensing.sense_patch` gives for B poses); until the next
        call, the N looked-up states are B equal groups of rows, robot-major, group ``b`` reading map ``b``."""
        if occupied.ndim != 3 or tuple(occupied.shape[1:]) != tuple(self.patch_spec.shape):
            raise ValueError(f"set_maps takes [B, {', '.join(map(str, self.patch_spec.shape))}] patches, got "
                             f"{list(occupied.shape)}")
        with torch.no_grad():
            occupied = occupied.to(self.dtype)  # once for both encoders (each converts only what is not yet)
            embedding = self.encode(occupied)  # [B, E]
            level_term, self._w_state, self._layers = self._folded_weights()
            # W_e e + b + w_t t / T per map and level: a lookup is one addmm (summed in this order, as always)
            self._map_bias = (self.inp_x.bias + self.inp_e(embedding)[:, None, :] + level_term).detach()
            if self.local is not None:
                self._local_map = self.encode_local(occupied).detach()  # [B, C, H, W]
        self.encodes += 1

    def _folded_weights(self) -> tuple[Tensor, Tensor, list[tuple[Tensor, Tensor]]]:
        """What a lookup needs of the weights alone, made once per set of weights rather than per map: the level
        term ``w_t t / T`` ``[T+1, Hd]``, ``W_x`` with the feature scales folded in (and ``W_l``: the sampled
        local features are more columns of the same addmm) ``[F-1 (+ P * C), Hd]``, and the body's
        ``(weight^T, bias)``. Remade when a parameter or buffer is another tensor or was written in place
        (training, ``load_state_dict``: each bumps the tensor's version counter)."""
        read = [self.inp_x.weight, self.inv_scale] + ([self.inp_l.weight] if self.inp_l is not None else [])
        for m in self.body:
            if isinstance(m, nn.Linear):
                read += [m.weight, m.bias]
        key = tuple((id(t), t.data_ptr(), t._version) for t in read)  # the tensors folded below
        cached = self._folded
        if cached is not None and cached[0] == key:
            return cached[1]
        w = self.inp_x.weight  # [Hd, F]: columns x_lin, cos, sin, t
        n_lin = len(self._linear)
        levels = torch.arange(self.horizon + 1, dtype=w.dtype, device=w.device) / self.horizon  # [T+1]
        level_term = (levels[:, None] * w[:, -1]).detach()  # [T+1, Hd]
        w_state = torch.cat((w[:, :n_lin] * self.inv_scale.index_select(0, self._linear_index), w[:, n_lin:-1]),
                            dim=1)
        if self.inp_l is not None:
            w_state = torch.cat((w_state, self.inp_l.weight), dim=1)
        layers = [(m.weight.detach().T.contiguous(), m.bias.detach()) for m in self.body if isinstance(m, nn.Linear)]
        folded = (level_term, w_state.T.contiguous().detach(), layers)
        self._folded = (key, folded)
        return folded

    @property
    def maps_set(self) -> int:
        """How many maps the last :meth:`set_map` / :meth:`set_maps` set (0: none)."""
        return 0 if self._map_bias is None else self._map_bias.shape[0]

    def clear_map(self) -> None:
        """Forget the map: lookups are refused until :meth:`set_map`."""
        self._map_bias = None

    def action_probs(self, x: Tensor, t: int) -> Tensor:
        """Softmax of the logits for the map last set: ``x [N, d]`` (policy dtype and device) at level ``t`` ->
        ``[N, A]``; states outside the box get the uniform row (module docstring). After :meth:`set_maps` of B
        maps, N must be a multiple of B (robot-major groups)."""
        if self._map_bias is None:
            raise ValueError("no map set: call set_map(patch) before looking up actions")
        assert self._w_state is not None  # set_maps sets it with the map bias
        check_query(x, t, self.horizon, self.config.state_dim, self.dtype, self.device)
        maps, n = self._map_bias.shape[0], x.shape[0]
        if n % maps:
            raise ValueError(f"{maps} maps are set: the {n} states must be {maps} equal groups (one per map)")
        with torch.no_grad():
            parts = [x.index_select(1, self._linear_index)]
            if self._angle:
                ang = x.index_select(1, self._angle_index)
                parts += [torch.cos(ang), torch.sin(ang)]
            if self.local is not None:  # dims 0, 1, 2 are x, y, heading (config check): cos / sin just made
                g = self.local.grid(x[:, :2], parts[-2][:, 0], parts[-1][:, 0])  # [N, P, 2]
                parts.append(self._read_local(g, maps))  # [N, P * C]
            bias = self._map_bias[0, t] if maps == 1 else self._map_bias[:, t].repeat_interleave(n // maps, dim=0)
            h = torch.addmm(bias, torch.cat(parts, dim=1), self._w_state)  # [N, Hd]
            for weight, layer_bias in self._layers:
                h = torch.addmm(layer_bias, torch.nn.functional.silu(h), weight)
            probs = torch.softmax(h, dim=1)  # [N, A]
            miss = self._count(x)  # [N]
            return torch.where(miss.unsqueeze(1), self._uniform, probs)

    def _read_local(self, g: Tensor, maps: int) -> Tensor:
        """The local features at probes ``g [N, P, 2]``, group ``b`` of the N rows reading map ``b``."""
        assert self.local is not None and self._local_map is not None
        if maps == 1:
            return self.local.read(self._local_map, g)
        n, probes = g.shape[0], g.shape[1]
        out = torch.nn.functional.grid_sample(self._local_map, g.view(maps, n // maps, probes, 2), mode="bilinear",
                                              padding_mode="zeros", align_corners=False)  # [B, C, n/B, P]
        return out.permute(0, 2, 3, 1).reshape(n, probes * self.local.channels)  # probe-major [N, P * C]

    def sample(self, x: Tensor, t: int, generator: torch.Generator | None) -> Tensor:
        """``x [N, d]`` at level ``t`` -> actions ``[N, q]`` drawn from :meth:`action_probs` (inverse CDF)."""
        return inverse_cdf_draw(self.action_probs(x, t).cumsum(dim=1), self.actions, generator)

    def draw(self, x: Tensor, t: int, r: Tensor) -> Tensor:
        """:meth:`sample` with the uniforms ``r [N]`` in ``[0, 1)`` given."""
        return inverse_cdf_pick(self.action_probs(x, t).cumsum(dim=1), self.actions, r)

    def fused_rollout(self, system: System, x0: Tensor, num_samples: int, horizon: int,
                      generator: torch.Generator | None,
                      uniforms: Tensor | None = None) -> tuple[Tensor, Tensor] | None:
        """The rollout's own loop, when it has one for this start (:func:`~cuniform_torch.sampling.rollout.rollout`
        asks): on a CPU, float32, with numba, for a :class:`~cuniform_torch.systems.models.Dubins` system (its own
        speed and time step), the start-frame states ``[T+1, 3, N]`` (time-major) and actions ``[N, T, q]`` of
        :mod:`~cuniform_torch.maps.kernels` (the step-by-step path's draws, to float rounding); else None.
        ``uniforms [T, N]`` in ``[0, 1)``, when given, are the draws (else they come from ``generator``)."""
        on_cpu = generator is None or generator.device.type == "cpu"
        if not (self.compiled and self.maps_set == 1 and x0.ndim == 1 and type(system) is Dubins and on_cpu
                and x0.dtype == self.dtype and kernels.usable(x0.device, self.dtype)):
            return None
        assert self._map_bias is not None and self._w_state is not None  # maps_set == 1: set_maps set both
        local = self.local
        geometry = dict(dt=system.dt, speed=system.speed, origin_x=self.patch_spec.origin[0],
                        origin_y=self.patch_spec.origin[1], resolution=self.patch_spec.resolution,
                        half_x=self._box_floats[0][0], half_y=self._box_floats[0][1],
                        cell_x=self._box_floats[1][0], cell_y=self._box_floats[1][1])
        states, actions, near, miss = kernels.rollout_start_frame(
            self._map_bias[0], self._w_state, self._layers, self.actions,
            self._local_map if local is not None else None,
            local.probes if local is not None else torch.zeros((0, 2)), geometry, num_samples, horizon, generator,
            uniforms)
        self.counts.add_split(num_samples * horizon, near, miss)
        return states, actions

    def _count(self, x: Tensor) -> Tensor:
        """Count the lookups of ``x [N, d]`` (near the box: nearest hits; beyond it or not finite: misses);
        the misses ``bool [N]``."""
        if self._linear:
            excess = ((x.index_select(1, self._linear_index).abs() - self._box_half) / self._box_cell).amax(dim=1)
            near, miss = excess > 0, excess > 1
        else:
            near = miss = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        miss = miss | ~torch.isfinite(x).all(dim=1)  # NaN compares False above: caught here
        self.counts.add_split(x.shape[0], (near & ~miss).sum(), miss.sum())
        return miss

    def _apply(self, fn, recurse: bool = True):  # .to(device) moves the counters; the folded map is derived from
        super()._apply(fn, recurse)             # the weights, so it is dropped (set_map again)
        self._map_bias, self._w_state, self._layers, self._local_map, self._folded = None, None, [], None, None
        self.counts.to(self.device)
        return self

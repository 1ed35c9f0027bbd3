"""``learned_dubins``: a Dubins robot whose ``step`` is a small MLP trained on the true Dubins step.

The costly-dynamics mode of the navigation benchmark (issue 36): every method's rollouts step this model, which
defines no ``scan``, so the per-step loop runs and rollouts dominate a command's time, as with a learned model in
practice. Same parameters, action set, cells and grid as :class:`~cuniform_torch.systems.models.Dubins`, so the
Dubins robot's C-Uniform tables still serve it (they look up the learned states).

The MLP (1 -> H -> H -> 3, tanh) maps the turn rate (scaled to [-1, 1]) to the body-frame displacement and the
heading change of one step (scaled by ``speed dt`` and ``max_omega dt``); ``step`` rotates the displacement by
the current heading. The heading enters only through that rotation, so the model is SE(2)-invariant by
construction (``se2_invariant = True`` holds exactly, not only approximately).

Training: ``train_samples`` turn rates drawn uniformly from ``[-max_omega, max_omega]`` (seeded generator), full-batch
Adam in float64 for ``train_steps`` steps on one thread: deterministic on a CPU for a seed, about a second. The
weights are rebuilt on construction and kept per process (keyed by the parameters), not written to disk.

Shapes: N samples, H hidden units.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from cuniform_torch.common.checks import non_negative, positive, positive_int
from cuniform_torch.systems.models import _check_grid, _check_step_inputs, _evenly, _params
from cuniform_torch.systems.protocol import MAX_ACTIONS

__all__ = ["LearnedDubins", "dubins_body_step", "train_weights"]

_MAX_HIDDEN = 1024
_MAX_TRAIN_STEPS = 100_000


def dubins_body_step(rate: Tensor, speed: float, dt: float) -> Tensor:
    """The true Dubins step in the body frame: ``rate [N]`` -> ``[N, 3]`` (forward, left, heading change).

    Dubins turns first, then moves along the new heading: ``(v dt cos(w dt), v dt sin(w dt), w dt)``."""
    turn = rate * dt  # [N]
    return torch.stack((speed * dt * torch.cos(turn), speed * dt * torch.sin(turn), turn), dim=1)


@functools.lru_cache(maxsize=16)
def train_weights(speed: float, dt: float, max_omega: float, hidden: int, seed: int, train_samples: int,
                  train_steps: int) -> tuple[Tensor, ...]:
    """The trained MLP's float64 weights ``(W1 [1, H], b1 [H], W2 [H, H], b2 [H], W3 [H, 3], b3 [3])`` (module
    docstring); cached per process for the same arguments."""
    gen = torch.Generator().manual_seed(seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one thread: the same sums in the same order, so the same weights on any CPU count
    try:
        # enabled here: the first step may come inside a controller's no-grad or inference-mode command
        with torch.inference_mode(False), torch.enable_grad():
            rate = (torch.rand(train_samples, dtype=torch.float64, generator=gen) * 2.0 - 1.0) * max_omega  # [M]
            feats = _features(rate, max_omega)  # [M, 1]
            target = dubins_body_step(rate, speed, dt) / _out_scale(speed, dt, max_omega, torch.float64)  # [M, 3]

            def init(fan_in: int, fan_out: int) -> tuple[Tensor, Tensor]:
                bound = 1.0 / math.sqrt(fan_in)
                w = (torch.rand(fan_in, fan_out, dtype=torch.float64, generator=gen) * 2 - 1) * bound
                b = (torch.rand(fan_out, dtype=torch.float64, generator=gen) * 2 - 1) * bound
                return w.requires_grad_(), b.requires_grad_()

            params = [*init(1, hidden), *init(hidden, hidden), *init(hidden, 3)]
            opt = torch.optim.Adam(params, lr=1e-2)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=train_steps, eta_min=1e-5)
            for _ in range(train_steps):  # full batch: no sampling order to seed
                opt.zero_grad(set_to_none=True)
                loss = torch.mean((_mlp(feats, params) - target) ** 2)
                loss.backward()
                opt.step()
                sched.step()
    finally:
        torch.set_num_threads(threads)
    return tuple(p.detach() for p in params)


def _features(rate: Tensor, max_omega: float) -> Tensor:
    """``rate [N]`` -> ``[N, 1]`` scaled to [-1, 1] (a robot that cannot turn: all zeros)."""
    return (rate / max_omega if max_omega > 0 else rate * 0.0).unsqueeze(1)


def _out_scale(speed: float, dt: float, max_omega: float, dtype: torch.dtype, device: Any = None) -> Tensor:
    """``[3]``: the scales of the body-frame step, so every output of the MLP is of order 1."""
    return torch.tensor([speed * dt, speed * dt, max(max_omega, 1e-6) * dt], dtype=dtype, device=device)


def _mlp(feats: Tensor, params: list[Tensor] | tuple[Tensor, ...]) -> Tensor:
    """``feats [N, 1]`` -> ``[N, 3]``: two tanh layers and a linear one."""
    w1, b1, w2, b2, w3, b3 = params
    h = torch.tanh(torch.addmm(b1, feats, w1))  # [N, H]
    h = torch.tanh(torch.addmm(b2, h, w2))  # [N, H]
    return torch.addmm(b3, h, w3)  # [N, 3]


@dataclass(frozen=True)
class LearnedDubins:
    """A Dubins car ``(x, y, theta)`` whose step is a trained MLP (module docstring).

    :param speed: forward speed v of the modelled Dubins robot (m/s)
    :param dt: time step (s)
    :param max_omega: the actions are ``num_actions`` turn rates evenly in ``[-max_omega, max_omega]`` (rad/s)
    :param num_actions: number of turn rates
    :param cell_size: grid cell size (m, m, rad); the angle size must be 2*pi/K
    :param cell_offset: grid offset in cells (|offset| < 0.5)
    :param hidden: units of each of the MLP's two hidden layers
    :param seed: seed of the training data and the initial weights
    :param train_samples: turn rates sampled for training
    :param train_steps: full-batch Adam steps
    """

    speed: float = 1.0
    dt: float = 0.2
    max_omega: float = math.pi / 4
    num_actions: int = 5
    cell_size: tuple[float, ...] = (0.05, 0.05, 2.0 * math.pi / 40)
    cell_offset: tuple[float, ...] = (0.0, 0.0, 0.01)
    hidden: int = 64
    seed: int = 0
    train_samples: int = 512
    train_steps: int = 2000

    name: ClassVar[str] = "learned_dubins"
    periodic: ClassVar[tuple[bool, ...]] = (False, False, True)
    se2_invariant: ClassVar[bool] = True  # the heading enters only as the rotation of a body-frame step
    column_major_ok: ClassVar[bool] = True  # step indexes columns

    def __post_init__(self) -> None:
        positive(self.name, speed=self.speed, dt=self.dt)
        non_negative(self.name, max_omega=self.max_omega)
        positive_int(self.name, "num_actions", self.num_actions, at_most=MAX_ACTIONS)
        positive_int(self.name, "hidden", self.hidden, at_most=_MAX_HIDDEN)
        positive_int(self.name, "train_samples", self.train_samples, at_most=1 << 20)
        positive_int(self.name, "train_steps", self.train_steps, at_most=_MAX_TRAIN_STEPS)
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"{self.name}: seed must be an integer >= 0, got {self.seed!r}")
        _check_grid(self)
        object.__setattr__(self, "_by_place", {})  # (dtype, device) -> weights there: converted once

    @classmethod
    def of(cls, dubins: Any, **kwargs: Any) -> LearnedDubins:
        """The learned model of a :class:`~cuniform_torch.systems.models.Dubins` system (its parameters and grid);
        ``kwargs`` set the training fields (``hidden``, ``seed``, ...)."""
        if getattr(dubins, "name", None) != "dubins":
            raise ValueError(f"LearnedDubins.of needs a 'dubins' system, got {getattr(dubins, 'name', dubins)!r}")
        return cls(**dubins.params(), **kwargs)

    @property
    def state_dim(self) -> int:
        return 3

    def weights(self, dtype: torch.dtype = torch.float64, device: Any = None) -> tuple[Tensor, ...]:
        """The MLP's weights (``train_weights``) in ``dtype`` on ``device``."""
        key = (dtype, str(device) if device is not None else "cpu")
        by_place: dict = self._by_place  # type: ignore[attr-defined]
        if key not in by_place:
            w = train_weights(float(self.speed), float(self.dt), float(self.max_omega), self.hidden, self.seed,
                              self.train_samples, self.train_steps)
            by_place[key] = tuple(t.to(dtype=dtype, device=device) for t in w) + (
                _out_scale(self.speed, self.dt, self.max_omega, dtype, device),)
        return by_place[key]

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[A, 1]`` turn rates, evenly in ``[-max_omega, max_omega]`` (as Dubins)."""
        return _evenly(-self.max_omega, self.max_omega, self.num_actions).to(dtype=dtype, device=device).unsqueeze(1)

    def body_step(self, rate: Tensor) -> Tensor:
        """``rate [N]`` -> ``[N, 3]``: the MLP's body-frame step (forward, left, heading change)."""
        *params, scale = self.weights(rate.dtype, rate.device)
        return _mlp(_features(rate, self.max_omega), params) * scale  # [N, 3]

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """``x [N, 3]``, ``u [N, 1]`` -> ``[N, 3]``: the body-frame step rotated by the heading, heading wrapped."""
        _check_step_inputs(self, x, u, 1)
        d = self.body_step(u[:, 0])  # [N, 3]
        c, s = torch.cos(x[:, 2]), torch.sin(x[:, 2])  # [N]
        theta = torch.remainder(x[:, 2] + d[:, 2] + math.pi, 2.0 * math.pi) - math.pi  # wrap_angle's arithmetic
        return torch.stack((x[:, 0] + c * d[:, 0] - s * d[:, 1], x[:, 1] + s * d[:, 0] + c * d[:, 1], theta), dim=1)

    def params(self) -> dict[str, Any]:
        return _params(self)

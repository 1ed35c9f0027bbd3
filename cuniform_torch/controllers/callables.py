"""pytorch_mppi's convention on the MPPI core: a dynamics function instead of a System, a per-step running cost
instead of a trajectory cost, a noise covariance, action bounds, ``u_init`` / ``U_init``.

Shapes: B robots, K samples per robot, T horizon, d (pytorch_mppi's ``nx``) state dimensions, q (``nu``) action
dimensions, N = B*K*T rows of a running cost's one call.

The pieces, each small, that :class:`~cuniform_torch.controllers.mppi.MPPI` (given a function and pytorch_mppi's
keywords) and the drop-in :mod:`cuniform_torch.pytorch_mppi` put on the core:

* :class:`DynamicsSystem`: a dynamics function ``(state [K, d], action [K, q]) -> [K, d]`` with its state size and
  action bounds, as the core's System. It has no grid (no cell sizes): MPPI reads no table.
* :class:`RunningCost`: a per-step ``running_cost(state, action) -> [K]`` of the *next* state and the action that
  led there (pytorch_mppi's), and its ``terminal_state_cost(states [1, K, T, d], actions [1, K, T, q])``, as one
  batched trajectory cost ``[B, K, T+1, d]`` -> ``[B, K]``. The running cost is called ONCE per command, on all
  B*K*T (state, action) rows flattened (pytorch_mppi calls it T times on K rows): it must be row-wise.
* :class:`CallableProposal`: MPPI's Gaussian proposal with pytorch_mppi's noise (a full covariance through its
  Cholesky factor, a mean ``noise_mu``), bounds that may be infinite, ``u_init`` (the action appended when the
  nominal is shifted), ``U_init`` (the first nominal), the null action sample, and pytorch_mppi's control cost
  ``U Sigma^-1 eps`` (:meth:`CallableProposal.action_cost`, which the core weighs ``lambda * ...``).
* :func:`resolve`: pytorch_mppi's keyword arguments, checked once, turned into those pieces.
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any, Protocol

import torch
from torch import Tensor

from cuniform_torch.controllers.checks import _callable_name
from cuniform_torch.controllers.proposals import GaussianProposal, _start_rows
from cuniform_torch.controllers.result import MPPIResult
from cuniform_torch.controllers.streams import RobotStreams
from cuniform_torch.sampling.rollout import open_loop

__all__ = ["DynamicsFn", "RunningCostFn", "TerminalStateCostFn", "DynamicsSystem", "RunningCost", "CallableOptions",
           "CallableProposal", "Resolved", "resolve", "is_system", "covariance_to_noise"]


class DynamicsFn(Protocol):
    """pytorch_mppi's dynamics: ``state [K, d]``, ``action [K, q]`` -> the next states ``[K, d]`` (a new tensor of
    the state's dtype and device)."""

    def __call__(self, state: Tensor, action: Tensor) -> Tensor: ...


class RunningCostFn(Protocol):
    """pytorch_mppi's per-step cost: ``state [K, d]`` (the state an action led to), ``action [K, q]`` -> ``[K]``
    (or ``[K, 1]``). Called on any number of rows at once: it must be row-wise."""

    def __call__(self, state: Tensor, action: Tensor) -> Tensor: ...


class TerminalStateCostFn(Protocol):
    """pytorch_mppi's terminal cost, as its ``MPPI`` calls it: ``states [1, K, T, d]`` (the states after each
    step; not the start), ``actions [1, K, T, q]`` -> ``[1, K]`` or ``[K]``."""

    def __call__(self, states: Tensor, actions: Tensor) -> Tensor: ...


def is_system(obj: object) -> bool:
    """Whether ``obj`` is given as a System (it has ``step`` and ``action_set``), not as a dynamics function."""
    return callable(getattr(obj, "step", None)) and callable(getattr(obj, "action_set", None))


# ------------------------------------------------------------------------------------------ the dynamics

class DynamicsSystem:
    """A dynamics function as the System the MPPI core reads: its state dimension (``periodic``: none), its action
    bounds and ``step``. ``u_scale`` multiplies the actions before the function sees them (pytorch_mppi's).

    There is no grid: ``cell_size`` and ``cell_offset`` raise AttributeError saying so (a C-Uniform table needs a
    System with cell sizes), and ``dt`` is None (LowPassMPPI's ``cutoff`` needs one: give ``a``).

    :param dynamics: ``(state [K, d], action [K, q]) -> [K, d]``
    :param nx: d, the state dimension
    :param low: ``[q]`` lower action bounds (float64, may be -inf)
    :param high: ``[q]`` upper bounds (may be +inf)
    :param u_scale: the factor applied to actions before ``dynamics``
    """

    name = "dynamics_fn"
    se2_invariant = False
    dt = None

    def __init__(self, dynamics: DynamicsFn, nx: int, low: Tensor, high: Tensor, u_scale: float = 1.0):
        self.dynamics = dynamics
        self.periodic = (False,) * nx
        self.state_dim = nx
        self.low, self.high = low, high
        self.u_scale = u_scale

    @property
    def cell_size(self) -> tuple[float, ...]:
        raise AttributeError(f"{_callable_name(self.dynamics)} is a dynamics function: it has no grid (cell sizes), "
                             "which only a C-Uniform table needs; for tables give a System (see "
                             "cuniform_torch.systems.System and the guide 'Your own robot')")

    @property
    def cell_offset(self) -> tuple[float, ...]:
        return self.cell_size

    def action_set(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[2, q]``: the bounds (a finite stand-in for an infinite one: the set only probes ``step`` once; the
        proposal clamps to the true bounds)."""
        low = torch.where(self.low.isfinite(), self.low,
                          torch.where(self.high.isfinite(), self.high - 1, torch.full_like(self.low, -1.0)))
        high = torch.where(self.high.isfinite(), self.high, low + 2)
        return torch.stack((low, high)).to(dtype=dtype, device=device)

    def step(self, x: Tensor, u: Tensor) -> Tensor:
        """``x [K, d]``, ``u [K, q]`` -> ``dynamics(x, u_scale * u)`` ``[K, d]``."""
        return self.dynamics(x, u if self.u_scale == 1 else u * self.u_scale)

    def params(self) -> dict[str, Any]:
        return {}


# ------------------------------------------------------------------------------------------ the cost

class RunningCost:
    """A per-step ``running_cost`` (and pytorch_mppi's ``terminal_state_cost``) as a batched trajectory cost:
    ``states [B, K, T+1, d]``, ``actions [B, K, T, q]`` -> ``[B, K]``, the sum over the steps of the cost of each
    next state with the action that led there. One call of ``running_cost`` on all ``B*K*T`` rows.

    :param running_cost: ``(state [N, d], action [N, q]) -> [N]`` (or ``[N, 1]``)
    :param terminal_state_cost: optional, ``(states [1, B*K, T, d], actions [1, B*K, T, q]) -> [1, B*K]`` (or
        ``[B*K]``)
    :param u_scale: the factor applied to actions before the costs see them (pytorch_mppi's)
    """

    batched = True
    """the core hands this cost every robot's rollouts as ``[B, K, ...]``"""

    def __init__(self, running_cost: RunningCostFn, terminal_state_cost: TerminalStateCostFn | None = None,
                 u_scale: float = 1.0):
        self.running_cost = running_cost
        self.terminal_state_cost = terminal_state_cost
        self.u_scale = u_scale

    def __call__(self, states: Tensor, actions: Tensor) -> Tensor:
        b, k, t1, d = states.shape
        t, q = t1 - 1, actions.shape[-1]
        nxt = states[:, :, 1:]  # [B, K, T, d]: the state each action led to
        u = actions if self.u_scale == 1 else actions * self.u_scale
        n = b * k * t
        out = self.running_cost(nxt.reshape(n, d), u.reshape(n, q))
        total = self._rows(out, "running_cost", self.running_cost, n, t, states).view(b, k, t).sum(dim=2)  # [B, K]
        if self.terminal_state_cost is not None:
            last = self.terminal_state_cost(nxt.reshape(1, b * k, t, d), u.reshape(1, b * k, t, q))
            total = total + self._rows(last, "terminal_state_cost", self.terminal_state_cost, b * k, None,
                                       states).view(b, k)
        return total

    @staticmethod
    def _rows(out: object, who: str, fn: object, n: int, t: int | None, like: Tensor) -> Tensor:
        """``out`` as ``[n]``: accepted ``[n]``, ``[n, 1]`` (a running cost) or ``[1, n]`` (a terminal cost), of
        ``like``'s dtype and device; ValueError naming ``fn`` otherwise."""
        if isinstance(out, Tensor):
            if (out.shape == (n, 1) and t is not None) or (out.shape == (1, n) and t is None):
                out = out.reshape(n)
            if out.shape == (n,) and out.dtype == like.dtype and out.device == like.device:
                return out
        got = (f"a {list(out.shape)} tensor of {out.dtype} on {out.device}" if isinstance(out, Tensor)
               else f"{type(out).__name__}")
        if t is not None:
            want = (f"[{n}] (one cost per row: it is called once per command on all {n} = robots x samples x "
                    f"{t} steps (state, action) rows)")
        else:
            want = f"[1, {n}] or [{n}] (one cost per rollout)"
        raise ValueError(f"{who} {_callable_name(fn)} returned {got}; expected {want} of {like.dtype} on "
                         f"{like.device}")


# ------------------------------------------------------------------------------------------ the proposal

@dataclasses.dataclass(frozen=True)
class CallableOptions:
    """pytorch_mppi's proposal settings, checked and as tensors (float64 on the CPU; the proposal casts them)."""

    low: Tensor | None = None
    """``[q]`` lower action bounds (may be -inf); None: the System's action set"""
    high: Tensor | None = None
    chol: Tensor | None = None
    """``[q, q]`` Cholesky factor of a full (non-diagonal) noise covariance; None: independent noise of std"""
    sigma_inv: Tensor | None = None
    """``[q, q]`` the inverse covariance, for the control cost"""
    noise_mu: Tensor | None = None
    """``[q]`` the noise's mean"""
    u_init: Tensor | None = None
    """``[q]`` appended when the nominal shifts; None: its last action repeated (this library's MPPI)"""
    U_init: Tensor | None = None
    """``[T, q]`` the first nominal; None: ``u_init`` (or zeros) at every step"""
    control_cost: bool = False
    """add pytorch_mppi's ``lambda * sum_t U_t Sigma^-1 eps_t`` to each sample's cost"""
    noise_abs_cost: bool = False
    """that cost with ``|eps|``"""
    shift_first: bool = False
    """pytorch_mppi's order: the nominal shifts at the start of a command (:meth:`CallableProposal.shift`, called by
    the drop-in), not after it"""
    sample_null_action: bool = False
    """sample 0 of each robot is the zero action sequence"""

    @property
    def needs_proposal(self) -> bool:
        """Whether anything here needs :class:`CallableProposal` (MPPI's Gaussian proposal does not do it)."""
        unbounded = self.low is not None and self.high is not None and not bool(
            (self.low.isfinite() & self.high.isfinite()).all())
        return unbounded or any(v is not None for v in (self.chol, self.noise_mu, self.u_init, self.U_init)) or any(
            (self.control_cost, self.shift_first, self.sample_null_action))


class CallableProposal(GaussianProposal):
    """MPPI's Gaussian proposal with pytorch_mppi's settings (:class:`CallableOptions`): ``clip(nominal + eps)``,
    ``eps ~ N(noise_mu, Sigma)`` (``Sigma = chol chol^T``, or ``diag(std^2)``), clipped to bounds that may be
    infinite; the warm start shifts in ``u_init`` (or repeats the last action); ``action_cost`` is the control cost.

    :param system: the dynamics (a System or a :class:`DynamicsSystem`)
    :param num_samples: K per robot
    :param horizon: T
    :param noise_std: ``[q]`` (or scalar) std; None: a quarter of each action range
    :param options: the settings
    :param device: where it runs
    :param dtype: its dtype
    :param num_robots: B
    """

    def __init__(self, system: Any, num_samples: int, horizon: int, noise_std: float | Tensor | None,
                 options: CallableOptions, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                 num_robots: int = 1):
        self.options = options
        super().__init__(system, num_samples, horizon, noise_std, device, dtype, num_robots)
        q = self.low.shape[0]
        dtype, device = self.dtype, self.device
        for name in ("noise_mu", "u_init"):
            value = getattr(options, name)
            if value is not None and value.shape != (q,):
                raise ValueError(f"{name} must have one value per action dimension ([{q}]), got {list(value.shape)}")
        if options.U_init is not None and options.U_init.shape != (self.horizon, q):
            raise ValueError(f"U_init must be [horizon, nu] = [{self.horizon}, {q}], got {list(options.U_init.shape)}")
        for name in ("chol", "sigma_inv"):
            value = getattr(options, name)
            if value is not None and value.shape != (q, q):
                raise ValueError(f"noise_sigma must be [{q}, {q}] for {q} action dimensions, got {list(value.shape)}")
        self.chol_t = None if options.chol is None else options.chol.T.to(dtype=dtype, device=device)  # [q, q]
        self.noise_mu = None if options.noise_mu is None else options.noise_mu.to(dtype=dtype, device=device)  # [q]
        self.u_init = None if options.u_init is None else options.u_init.to(dtype=dtype, device=device)  # [q]
        self._first = (torch.zeros((self.horizon, q), dtype=dtype, device=device) if options.U_init is None
                       else options.U_init.to(dtype=dtype, device=device))  # [T, q]
        if options.U_init is None and self.u_init is not None:
            self._first[:] = self.u_init
        self._nominal.copy_(self._first.expand_as(self._nominal))
        self.sigma_inv = None
        if options.control_cost:
            std = torch.as_tensor(self.std, dtype=torch.float64)
            inv = options.sigma_inv if options.sigma_inv is not None else torch.diag(std.square().reciprocal())
            if not bool(torch.isfinite(inv).all()):
                raise ValueError("the control cost (pytorch_mppi's lambda U Sigma^-1 eps) needs an invertible noise "
                                 f"covariance; the noise std is {std.tolist()}")
            self.sigma_inv = inv.to(dtype=dtype, device=device)  # [q, q]

    def _bounds(self, low: Tensor, high: Tensor) -> tuple[Tensor, Tensor]:
        opts = self.options
        if opts.low is None or opts.high is None:
            return low, high
        return opts.low.to(dtype=self.dtype, device=self.device), opts.high.to(dtype=self.dtype, device=self.device)

    def _noise(self, streams: RobotStreams, n: int) -> Tensor:
        """``[B, n, q]`` noise of mean ``noise_mu`` and covariance ``Sigma``, robot ``b``'s from its own stream."""
        z = streams.randn((n, self.low.shape[0]), self.dtype)  # [B, n, q]
        eps = z.mul_(self.std) if self.chol_t is None else z @ self.chol_t
        return eps if self.noise_mu is None else eps.add_(self.noise_mu)

    def propose_batch(self, states: Tensor, streams: RobotStreams) -> tuple[Tensor, Tensor]:
        b, k, t, q = states.shape[0], self.num_samples, self.horizon, self.low.shape[0]
        actions = self._sequences(streams, k, t).add_(self._nominal.unsqueeze(1))  # [B, K, T, q]
        if self.options.sample_null_action:
            actions[:, 0] = 0.0
        actions.clamp_(self.low, self.high)
        trajectories = open_loop(self.system, _start_rows(states, k), actions.view(b * k, t, q))  # [B*K, T+1, d]
        return trajectories.view(b, k, t + 1, -1), actions

    def action_cost(self, actions: Tensor) -> Tensor:
        """pytorch_mppi's control cost without its ``lambda``: ``sum_t U_t Sigma^-1 eps_t`` per sample, ``eps`` the
        clipped action minus the nominal ``U`` it was drawn around: ``[B, K, T, q]`` -> ``[B, K]``."""
        if self.sigma_inv is None:
            return actions.new_zeros(actions.shape[:2])
        eps = actions - self._nominal.unsqueeze(1)  # [B, K, T, q]
        if self.options.noise_abs_cost:
            eps = eps.abs_()
        weighted = self._nominal @ self.sigma_inv  # [B, T, q]: U_t Sigma^-1 (Sigma symmetric)
        return (eps * weighted.unsqueeze(1)).sum(dim=(2, 3))

    def _fill(self, nominal: Tensor) -> Tensor:
        """The appended step of a shift: ``u_init``, or each robot's last action: ``[B, 1, q]``."""
        return nominal[:, -1:] if self.u_init is None else self.u_init.expand(nominal.shape[0], 1, -1)

    def shift(self) -> None:
        """Shift every robot's nominal one step, appending ``u_init`` (in place)."""
        self._nominal.copy_(torch.cat((self._nominal[:, 1:], self._fill(self._nominal)), dim=1))

    def update(self, result: MPPIResult) -> None:
        """Warm start: each robot's weighted sequence, shifted one step (appending ``u_init``) unless
        ``shift_first`` (then the next command shifts it first, pytorch_mppi's order)."""
        nominal = result.nominal if result.nominal.ndim == 3 else result.nominal.unsqueeze(0)  # [B, T, q]
        if self.options.shift_first:
            self._nominal.copy_(nominal)
        else:
            self._nominal.copy_(torch.cat((nominal[:, 1:], self._fill(nominal)), dim=1))

    def reset(self, robots: Tensor | None = None) -> None:
        """The first nominal again (``U_init``, or ``u_init`` at every step) for ``robots`` (None: all)."""
        if robots is None:
            self._nominal.copy_(self._first.expand_as(self._nominal))
        else:
            self._nominal.index_copy_(0, robots.to(self.device),
                                      self._first.expand(robots.numel(), *self._first.shape).contiguous())


# ------------------------------------------------------------------------------------------ the arguments

def _vector(name: str, value: object) -> Tensor | None:
    """A number, sequence or tensor as a float64 CPU tensor (None stays None); ValueError naming ``name``."""
    if value is None:
        return None
    try:
        out = torch.as_tensor(value.detach().cpu() if isinstance(value, Tensor) else value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{name} must be a number, a sequence of numbers or a tensor, got {type(value).__name__}") \
            from None
    if not bool(torch.isfinite(out).all()) and name not in ("u_min", "u_max"):
        raise ValueError(f"{name} must be finite, got {out.tolist()}")
    return out


def covariance_to_noise(noise_sigma: object) -> tuple[Tensor, Tensor | None, Tensor]:
    """pytorch_mppi's ``noise_sigma`` (a covariance: a scalar variance, or ``[q, q]``) as ``(std [q] or [1],
    chol [q, q] or None, inverse [q, q])``: a diagonal covariance is independent noise of std ``sqrt(diag)``; a full
    one is kept through its Cholesky factor. ValueError for a vector (ambiguous), a non-symmetric or not positive
    definite matrix."""
    sigma = _vector("noise_sigma", noise_sigma)
    assert sigma is not None
    if sigma.ndim == 0:
        if not sigma > 0:
            raise ValueError(f"noise_sigma (a variance) must be > 0, got {sigma.item()}")
        return sigma.sqrt().reshape(1), None, sigma.reciprocal().reshape(1, 1)
    if sigma.ndim == 1:
        raise ValueError(f"noise_sigma is a covariance matrix [nu, nu] (pytorch_mppi's), got a vector "
                         f"{sigma.tolist()}: for one variance per action dimension pass torch.diag(v) (or "
                         f"noise_std=v.sqrt(), the standard deviations)")
    q = sigma.shape[0]
    if sigma.shape != (q, q):
        raise ValueError(f"noise_sigma must be a square [nu, nu] covariance, got {list(sigma.shape)}")
    if not torch.allclose(sigma, sigma.T, rtol=1e-6, atol=1e-12):
        raise ValueError(f"noise_sigma must be symmetric (a covariance), got {sigma.tolist()}")
    chol, info = torch.linalg.cholesky_ex(sigma)
    if int(info) != 0:
        raise ValueError(f"noise_sigma must be positive definite (a covariance with every variance > 0), got "
                         f"{sigma.tolist()}")
    std = sigma.diagonal().sqrt()
    full = bool((sigma - torch.diag(sigma.diagonal())).abs().max() > 0)
    return std, (chol if full else None), torch.cholesky_inverse(chol)


@dataclasses.dataclass
class Resolved:
    """pytorch_mppi-style arguments as the core's pieces."""

    system: Any
    """a System (the one given, or a :class:`DynamicsSystem`)"""
    cost_fn: Any
    noise_std: float | Tensor | None
    options: CallableOptions | None
    """None: nothing that MPPI's own Gaussian proposal does not do"""
    dtype: torch.dtype
    dynamics_fn: bool
    """the dynamics were given as a function"""


def _two_ways(who: str, fn: object) -> ValueError:
    return ValueError(
        f"{who} got the function {_callable_name(fn)} where a System was expected. Give the dynamics one of two ways: "
        f"a System (an object with step(x [N, d], u [N, q]) -> [N, d], action_set(), periodic: see "
        f"cuniform_torch.systems.System) with a trajectory cost cost_fn(states [N, T+1, d], actions [N, T, q]) -> [N]; "
        f"or the function itself, pytorch_mppi's way, with its state size and a per-step cost: "
        f"{who}(dynamics, nx=d, running_cost=cost, u_min=..., u_max=...) (or cuniform_torch.pytorch_mppi.MPPI, "
        f"pytorch_mppi's own signature)")


def resolve(who: str, system: object, cost_fn: object, *, nx: int | None = None, running_cost: object = None,
            terminal_state_cost: object = None, noise_std: object = None, noise_sigma: object = None,
            noise_mu: object = None, u_min: object = None, u_max: object = None, u_init: object = None,
            U_init: object = None, control_cost: bool | None = None, dtype: torch.dtype | None = None,
            u_scale: float = 1.0) -> Resolved:
    """Check pytorch_mppi's keyword arguments once and make the core's pieces of them (see the module). A System
    passes through (``nx`` must then match it, and its action set bounds the actions: no ``u_min`` / ``u_max``);
    a function becomes a :class:`DynamicsSystem`; ``running_cost`` (exclusive with ``cost_fn``) a
    :class:`RunningCost`. ``dtype`` None: ``noise_sigma``'s dtype when it is a floating tensor, else float32.
    ``control_cost`` None: on when ``noise_sigma`` is given (pytorch_mppi's algorithm), off otherwise."""
    fn_given = not is_system(system) and callable(system)
    if not is_system(system) and not fn_given:
        raise ValueError(f"{who}: the dynamics must be a System or a function (state [K, d], action [K, q]) -> "
                         f"[K, d], got {type(system).__name__}")
    if fn_given and nx is None:
        raise _two_ways(who, system)
    if nx is not None and (isinstance(nx, bool) or not isinstance(nx, numbers.Integral) or nx < 1):
        raise ValueError(f"nx (the state dimension) must be a positive integer, got {nx!r}")
    if not fn_given:
        d = len(tuple(getattr(system, "periodic", ())))
        if nx is not None and nx != d:
            raise ValueError(f"nx={nx} but the System {getattr(system, 'name', type(system).__name__)!r} has {d} "
                             f"state dimensions (leave nx out with a System)")
        if u_min is not None or u_max is not None:
            raise ValueError("u_min / u_max bound a dynamics function's actions; a System's action set bounds its "
                             "own (give the dynamics as a function, or leave them out)")
    if (cost_fn is None) == (running_cost is None):
        raise ValueError(f"{who}: give one cost: cost_fn(states [N, T+1, d], actions [N, T, q]) -> [N] (a trajectory "
                         f"cost) or running_cost(state [K, d], action [K, q]) -> [K] (per step, pytorch_mppi's)"
                         + ("; got both" if cost_fn is not None else ""))
    for name, fn in (("running_cost", running_cost), ("terminal_state_cost", terminal_state_cost)):
        if fn is not None and not callable(fn):
            raise TypeError(f"{name} must be callable, got {type(fn).__name__}")
    if terminal_state_cost is not None and running_cost is None:
        raise ValueError("terminal_state_cost(states [1, K, T, d], actions [1, K, T, q]) goes with running_cost "
                         "(pytorch_mppi's); with cost_fn give terminal_cost(states [N, d]) -> [N]")
    if noise_std is not None and noise_sigma is not None:
        raise ValueError("give noise_std (standard deviations) or noise_sigma (pytorch_mppi's covariance), not both")
    if isinstance(u_scale, bool) or not isinstance(u_scale, numbers.Real) or not float(u_scale) > 0:
        raise ValueError(f"u_scale must be a positive number, got {u_scale!r}")
    if dtype is None:
        dtype = (noise_sigma.dtype if isinstance(noise_sigma, Tensor) and noise_sigma.is_floating_point()
                 else torch.float32)
    chol = sigma_inv = None
    if noise_sigma is not None:
        std, chol, sigma_inv = covariance_to_noise(noise_sigma)
        noise_std = std
    if u_max is not None and u_min is None:  # pytorch_mppi: one bound given is the other's negative
        u_min = -_vector("u_max", u_max)  # type: ignore[operator]
    if u_min is not None and u_max is None:
        u_max = -_vector("u_min", u_min)  # type: ignore[operator]
    low, high = _vector("u_min", u_min), _vector("u_max", u_max)
    vectors = {"noise_mu": _vector("noise_mu", noise_mu), "u_init": _vector("u_init", u_init)}
    U0 = _vector("U_init", U_init)
    sizes = {name: v.shape[-1] for name, v in (("u_min", low), ("u_max", high), *vectors.items(), ("U_init", U0))
             if v is not None and v.ndim >= 1}
    if sigma_inv is not None:  # a 0-d covariance is one action dimension (pytorch_mppi's nu = 1)
        sizes["noise_sigma"] = sigma_inv.shape[0]
    if isinstance(noise_std, Tensor) and noise_std.numel() > 1 and noise_sigma is None:
        sizes["noise_std"] = noise_std.numel()
    if len(set(sizes.values())) > 1:
        raise ValueError(f"the action dimension differs between arguments: {sizes} (a 0-d noise_sigma is one "
                         f"dimension, as in pytorch_mppi: for q of them give a [q, q] covariance, e.g. "
                         f"v * torch.eye(q))")
    system_q = None if fn_given else check_action_dim(system)
    q = next(iter(sizes.values()), system_q or 1)
    if system_q is not None and q != system_q:
        raise ValueError(f"the System's actions have {system_q} dimensions but {sizes} say {q}")
    if fn_given:
        low = torch.full((q,), -torch.inf, dtype=torch.float64) if low is None else low.expand(q).clone()
        high = torch.full((q,), torch.inf, dtype=torch.float64) if high is None else high.expand(q).clone()
        if bool((low > high).any()) or low.isnan().any() or high.isnan().any():
            raise ValueError(f"u_min must be <= u_max, got u_min={low.tolist()}, u_max={high.tolist()}")
        system = DynamicsSystem(system, int(nx), low, high, float(u_scale))  # type: ignore[arg-type]
    elif u_scale != 1:
        raise ValueError("u_scale scales a dynamics function's actions; a System's step takes its own")
    if control_cost is None:
        control_cost = noise_sigma is not None
    if control_cost and noise_std is None:
        raise ValueError("control_cost (pytorch_mppi's lambda U Sigma^-1 eps) needs the noise's covariance: give "
                         "noise_sigma (or noise_std)")
    noise_mu_t, u_init_t = (None if v is None else v.expand(q).clone() for v in vectors.values())
    if U0 is not None and U0.ndim == 1 and q == 1:
        U0 = U0.unsqueeze(1)  # [T] for one action dimension
    if running_cost is not None:
        cost_fn = RunningCost(running_cost, terminal_state_cost, float(u_scale))  # type: ignore[arg-type]
    options = CallableOptions(
        low=low if fn_given else None, high=high if fn_given else None, chol=chol,
        sigma_inv=sigma_inv if control_cost else None, noise_mu=noise_mu_t, u_init=u_init_t, U_init=U0,
        control_cost=bool(control_cost))
    return Resolved(system, cost_fn, noise_std, options if options.needs_proposal else None, dtype, fn_given)


def check_action_dim(system: Any) -> int | None:
    """q of a System: its action set's columns (None when it has no ``[A, q]`` action set: the core's probe of the
    System then names what is wrong)."""
    actions = system.action_set(dtype=torch.float64)
    return int(actions.shape[1]) if isinstance(actions, Tensor) and actions.ndim == 2 else None


def with_options(resolved: Resolved, **changes: Any) -> CallableOptions:
    """``resolved``'s options (or the defaults) with ``changes``."""
    return dataclasses.replace(resolved.options or CallableOptions(), **changes)


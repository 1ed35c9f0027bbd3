"""The input checks of the MPPI core and its proposals (:mod:`cuniform_torch.controllers.mppi`,
:mod:`cuniform_torch.controllers.proposals`), and the cap on non-finite costs.

Each refuses bad input with one ValueError or TypeError naming it: a ``lambda_`` that the controller's dtype
cannot hold, a ``seed`` that is not an integer, a state of the wrong shape, dtype or device or with NaN, a
proposal's trajectories of the wrong shape, dtype or device, a user cost that is not a ``[K]`` tensor of the
controller's dtype and device. This module imports neither mppi nor proposals (both import it).
"""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from cuniform_torch.common.checks import check_positive_int as check_positive_int  # re-exported (proposals, mppi)
from cuniform_torch.sampling.rollout import same_device

COST_CAP = 1e10
"""NaN / inf costs are replaced by this finite value before weighting"""


def seeded_generator(seed: int | None, device: torch.device) -> torch.Generator:
    """A ``torch.Generator`` on ``device``: seeded with ``seed``, or from fresh entropy when it is None."""
    generator = torch.Generator(device=device)
    generator.manual_seed(seed) if seed is not None else generator.seed()
    return generator


def _check_dtype(dtype: object) -> torch.dtype:
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(f"dtype must be a floating-point torch.dtype, got {dtype!r}")
    return dtype


def _finite_costs(costs: Tensor) -> Tensor:
    """NaN and +inf -> COST_CAP, -inf -> -COST_CAP, everything capped at COST_CAP."""
    return torch.nan_to_num(costs, nan=COST_CAP, posinf=COST_CAP, neginf=-COST_CAP).clamp_(max=COST_CAP)


def _check_lambda(lambda_: float, dtype: torch.dtype) -> float:
    """``lambda_`` as a float: 0, or a positive number that ``dtype`` holds as a normal number with a finite
    inverse (else ``-(c - min) / lambda`` is 0 / 0 or inf - inf in that dtype, and the weights are NaN)."""
    if isinstance(lambda_, bool) or not isinstance(lambda_, numbers.Real) or not (math.isfinite(lambda_) and lambda_ >= 0):
        raise ValueError(f"lambda_ must be a finite number >= 0, got {lambda_!r}")
    value = float(lambda_)
    if value == 0:
        return value
    held = torch.tensor(value, dtype=dtype).item()  # lambda_ as the controller's dtype rounds it
    inverse = torch.tensor(1.0 / held, dtype=dtype).item() if held > 0 else math.inf
    if not (held >= torch.finfo(dtype).tiny and math.isfinite(held) and math.isfinite(inverse)):
        info = torch.finfo(dtype)
        raise ValueError(f"lambda_={lambda_!r} is out of range for {dtype}: it must be 0 or between {info.tiny:.3g} "
                         f"and {info.max:.3g} with a finite 1/lambda_ (it becomes {held!r} in {dtype})")
    return value


def _callable_name(fn: object) -> str:
    """A user callable's name for an error message: its ``__qualname__``, else a short repr."""
    name = getattr(fn, "__qualname__", None)
    if isinstance(name, str):
        return name
    text = repr(fn)
    return text if len(text) <= 80 else f"{type(fn).__qualname__} object"


def _check_costs(costs: object, who: str, fn: object, shape: tuple[int, ...], dtype: torch.dtype,
                 device: torch.device) -> Tensor:
    """``costs`` as returned by the user's ``fn``, checked to be a tensor of ``shape`` (``(K,)``, ``(B*K,)`` or
    ``(B, K)``), ``dtype`` and ``device`` (shape, dtype and device only: no host sync)."""
    want = "[" + ", ".join(map(str, shape)) + "]"
    per = ("one cost per rollout of every robot" if len(shape) == 1
           else "one cost per rollout, per robot: this cost says batched = True")
    expected = f"expected a {want} tensor of {dtype} on {device} ({per}; the controller's dtype and device)"
    if not isinstance(costs, Tensor):
        raise ValueError(f"{who} {_callable_name(fn)} returned {type(costs).__name__} {costs!r:.60}; {expected}")
    if costs.shape != shape or costs.dtype != dtype or not same_device(costs.device, device):
        hint = ""
        if costs.ndim == len(shape) + 1 and costs.shape[:-1] == shape:  # [N, T] (or [B, K, T]): a cost per step
            hint = (f" (a {list(costs.shape)} tensor is a cost per step: sum it over the steps, "
                    f"{who}(...).sum(dim=-1); or give a per-step cost(state [K, d], action [K, q]) -> [K] as "
                    f"running_cost=, pytorch_mppi's way)")
        raise ValueError(f"{who} {_callable_name(fn)} returned a {list(costs.shape)} tensor of {costs.dtype} on "
                         f"{costs.device}; {expected}{hint}")
    return costs.detach()


def _describe(x: object) -> str:
    return f"{list(x.shape)} {x.dtype} on {x.device}" if isinstance(x, Tensor) else type(x).__name__


def check_state_batch(state: object, num_robots: int, state_dim: int, dtype: torch.dtype, device: torch.device,
                      values: bool) -> tuple[Tensor, bool]:
    """``state [B, d]`` (B = ``num_robots``) or, for one robot, ``[d]``, of the controller's dtype and device;
    finite when ``values`` (a host read). Returns it detached as ``[B, d]`` and whether a ``[d]`` state was given."""
    shapes = f"[{num_robots}, {state_dim}]" + (f" or [{state_dim}]" if num_robots == 1 else "")
    if not isinstance(state, Tensor):
        fix = ""
        if type(state).__module__ == "numpy" or isinstance(state, (list, tuple)):
            fix = (f": pass torch.as_tensor(state, dtype={dtype}, device={str(device)!r}), or build the controller "
                   f"with convert_states=True (a numpy state is then converted once and the command comes back as "
                   f"a numpy array)")
        raise ValueError(f"state must be a tensor of shape {shapes}, got {type(state).__name__}{fix}")
    single = state.ndim == 1 and num_robots == 1
    if state.shape != (num_robots, state_dim) and not (single and state.shape == (state_dim,)):
        more = (f" (this controller has {num_robots} robots: num_robots sets it)"
                if state.ndim == 2 and state.shape[1] == state_dim else "")
        raise ValueError(f"state must be a tensor of shape {shapes}, got {list(state.shape)}{more}")
    if not same_device(state.device, device):
        raise ValueError(f"state is on {state.device} but the controller is on {device}")
    if state.dtype != dtype:
        raise ValueError(f"state is {state.dtype} but the controller is {dtype}; pass state.to({dtype}), or build the "
                         f"controller with dtype={state.dtype} (or convert_states=True: converted per command, the "
                         f"command back in the state's dtype)")
    state = state.detach()
    if single:
        state = state.unsqueeze(0)
    if values and not bool(torch.isfinite(state).all()):
        bad = torch.nonzero(~torch.isfinite(state).all(dim=1)).flatten().tolist()
        raise ValueError(f"state contains NaN or infinite values (robots {bad[:8]}): {state[bad[0]].tolist()}")
    return state, single


def check_proposals(who: str, states: object, actions: object, shape: tuple[int, ...], dtype: torch.dtype,
                    device: torch.device) -> None:
    """What ``who.propose`` returned: ``[(B,) K, T+1, d]`` states and ``[(B,) K, T, q]`` actions (``shape`` is
    ``(B, K, T, d, q)``, or ``(K, T, d, q)`` for a proposal of one robot) of ``dtype`` on ``device``."""
    *lead, t, d, q = shape
    want_states, want_actions = (*lead, t + 1, d), (*lead, t, q)
    ok = (isinstance(states, Tensor) and isinstance(actions, Tensor) and states.shape == want_states
          and actions.shape == want_actions and states.dtype == actions.dtype == dtype
          and same_device(states.device, device) and same_device(actions.device, device))
    if not ok:
        raise ValueError(f"{who}.propose returned states {_describe(states)} and actions "
                         f"{_describe(actions)}; expected {list(want_states)} and {list(want_actions)} of "
                         f"{dtype} on {device}")

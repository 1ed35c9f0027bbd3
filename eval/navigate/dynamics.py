"""The dynamics the benchmark's controllers plan with (``--dynamics``): the robot's own, or a learned model of it.

``learned`` (issue 36, the costly-dynamics mode): every method's rollouts step
:class:`~cuniform_torch.systems.learned.LearnedDubins`, a small MLP trained on the robot's Dubins step. It has no
closed-form ``scan`` and no compiled rollout of the tables or the map policy (those serve the ``Dubins`` class only),
so every method runs the step loop and rollouts dominate a command's time. The tables stay the robot's: same action
set, cells and grid, and they look up the learned states.

The simulator keeps the TRUE dynamics: the controllers plan with a model that is slightly wrong (a fraction of a
millimetre a step, :mod:`tests.test_learned_dynamics`), as a learned model is in practice, and the outcomes stay
those of the real robot, comparable with the true-dynamics runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from cuniform_torch.systems.learned import LearnedDubins
from eval.common.methods import Sources

__all__ = ["DYNAMICS", "LearnedSources", "learned_model"]

DYNAMICS = ("true", "learned")
"""the values of ``--dynamics``"""


def learned_model(system: Any) -> LearnedDubins:
    """The learned model of the robot's ``system`` (a ``dubins`` system); a ValueError naming any other."""
    if getattr(system, "name", None) != "dubins":
        raise ValueError(f"--dynamics learned models the Dubins robot only; this robot is "
                         f"{getattr(system, 'name', type(system).__name__)!r} (leave --dynamics out)")
    model = LearnedDubins.of(system)
    model.weights()  # trained now (about 2 s, once a process), not inside the first timed command
    return model


@dataclass
class LearnedSources(Sources):
    """:class:`~eval.common.methods.Sources` whose every loaded policy, and ``system``, is the learned model of the
    table's system; ``true_system`` is the table's own (what the simulator steps)."""

    def load(self, source: str) -> Any:
        self.true_system  # noqa: B018 (kept before a loaded table's system is replaced)
        obj = super().load(source)
        if getattr(obj, "system", None) is not None and not isinstance(obj.system, LearnedDubins):
            obj.system = self.system  # the policy's lookups and draws stay; its rollouts step the model
        return obj

    @property
    def true_system(self) -> Any:
        if "true" not in self._cache:
            self._cache["true"] = Sources.system.fget(self)  # type: ignore[attr-defined]
        return self._cache["true"]

    @property  # type: ignore[override]
    def system(self) -> LearnedDubins:
        if "learned" not in self._cache:
            self._cache["learned"] = learned_model(self.true_system)
        return self._cache["learned"]

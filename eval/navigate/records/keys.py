"""The key an episode record is stored and resumed under: what the runner writes and every reader looks up."""

from __future__ import annotations

__all__ = ["episode_key"]


def episode_key(suite: str, task_id: int, method: str, budget: int, repeat: int) -> str:
    """The key a record is stored and resumed under: ``suite/task_id/method/budget/repeat``."""
    return f"{suite}/{task_id}/{method}/{budget}/{repeat}"

"""``python -m eval.bench family --clock thread``: a command's CPU time, not the time it waited (a loaded machine)."""

from __future__ import annotations

import time

import torch

from eval.bench.family import time_round_robin


def test_the_thread_clock_leaves_out_waiting():
    fns = {"waits": lambda: time.sleep(0.02)}  # 20 ms asleep, next to no CPU time
    wall = time_round_robin(fns, repeats=3, warmup=0, device=torch.device("cpu"))
    cpu = time_round_robin(fns, repeats=3, warmup=0, device=torch.device("cpu"), clock="thread")
    assert wall["waits"] >= 0.019 and cpu["waits"] < 0.005


def test_the_least_round_is_the_minimum():
    waits = iter([0.03, 0.0, 0.03])
    fns = {"varies": lambda: time.sleep(next(waits))}
    least = time_round_robin(fns, repeats=3, warmup=0, device=torch.device("cpu"), stat="min")
    assert least["varies"] < 0.01  # the round that did not sleep; the median of the three sleeps 30 ms

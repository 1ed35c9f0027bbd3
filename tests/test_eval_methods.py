"""The one method registry of eval (``eval.common.methods``): each benchmark's keys resolve to its methods, a
method two benchmarks share is one object, each benchmark keeps the labels its records print, and a wrong key,
a key named twice or an unknown benchmark is refused with one clear error."""

from __future__ import annotations

import pytest

from cuniform_torch import MPPI
from cuniform_torch.sampling import GaussianSampler
from eval.common.methods import (
    BENCHMARKS,
    METHODS,
    NAVIGATE,
    PAPER,
    Method,
    gaussian_baselines,
    methods_of,
    parse_methods,
)

PAPER_KEYS = ["mppi_low", "mppi_medium", "mppi_high", "log_mppi_low", "log_mppi_medium", "log_mppi_high", "mppi_1.0",
              "mppi_pink_1.0", "mppi_lowpass_1.0", "smppi_2.0", "kmppi_1.0", "uniform", "cu_table", "cu_coverage",
              "cu_mlp", "cu_graph", "cumppi", "mix_cu_mppi_0.5"]
PAPER_OPT_IN = ["mppi_1.0", "mppi_pink_1.0", "mppi_lowpass_1.0", "smppi_2.0", "kmppi_1.0", "mix_cu_mppi_0.5"]
"""the navigation robot's proposals, in the paper's open-loop experiments by name only (issue 36)"""
NAV_KEYS = ["mppi_0.1", "mppi_0.3", "mppi_1.0", "log_mppi_0.3", "mppi_pink_1.0", "mppi_lowpass_1.0", "smppi_2.0",
            "kmppi_1.0", "uniform", "cu_table", "cu_coverage", "cu_mlp", "cumppi", "cumppi_pipe", "mix_cu_mppi_0.5",
            "cfu_mppi"]
SHARED = ["uniform", "cu_table", "cu_coverage", "cu_mlp", "cumppi", *PAPER_OPT_IN]

NAV_LABELS = {"mppi_0.1": "MPPI (std 0.1)", "mppi_0.3": "MPPI (std 0.3)", "mppi_1.0": "MPPI (std 1.0)",
              "log_mppi_0.3": "log-MPPI (std 0.3)", "mppi_pink_1.0": "MPPI, pink noise (std 1.0)",
              "mppi_lowpass_1.0": "MPPI, low-pass noise (std 1.0, a 0.8)",
              "smppi_2.0": "smooth MPPI (rate std 2.0 rad/s^2)", "kmppi_1.0": "kernel MPPI (7 control points, std 1.0)",
              "mix_cu_mppi_0.5": "mixture: half C-Uniform table, half MPPI std 1.0", "uniform": "uniform discrete actions",
              "cu_table": "C-Uniform (max-flow table)", "cu_coverage": "C-Uniform (coverage table)",
              "cu_mlp": "C-Uniform (distilled MLP)", "cumppi": "CU-MPPI (max-flow table)",
              "cumppi_pipe": "CU-MPPI in one pass (max-flow table)", "cfu_mppi": "CFU-MPPI (map-conditioned policy)"}
"""what a navigation run's results.json ``labels`` and its figures print: a change here changes its outputs"""
PAPER_LABELS = {"uniform": "uniform discrete actions", "cu_table": "C-Uniform table (max-flow)",
                "cu_coverage": "C-Uniform table (coverage method)", "cu_mlp": "C-Uniform distilled MLP",
                "cumppi": "CU-MPPI (max-flow table)", "mppi_low": "MPPI low (std 0.03)"}


def test_each_benchmark_has_its_keys_and_every_method_belongs_to_one():
    assert list(methods_of(PAPER)) == PAPER_KEYS
    assert list(methods_of(NAVIGATE)) == NAV_KEYS
    assert sorted(METHODS) == sorted(set(PAPER_KEYS) | set(NAV_KEYS))
    assert all(m.key == k and m.benchmarks and set(m.benchmarks) <= set(BENCHMARKS) for k, m in METHODS.items())


def test_every_key_resolves_in_its_benchmark_and_the_defaults_are_kept():
    nav = parse_methods(NAV_KEYS, benchmark=NAVIGATE, closed_loop=True)
    assert [m.key for m in nav] == NAV_KEYS
    closed = [k for k in PAPER_KEYS if k != "cu_graph"]
    opened = [k for k in PAPER_KEYS if k != "cumppi"]
    assert [m.key for m in parse_methods(closed, benchmark=PAPER, closed_loop=True)] == closed
    assert [m.key for m in parse_methods(opened, benchmark=PAPER, closed_loop=False)] == opened
    # defaults: the navigation benchmark leaves its opt-in methods out; the paper's experiments take all that apply
    # (its closed loop drops the slow cu_mlp itself, eval.paper.episodes)
    assert [m.key for m in parse_methods(None, benchmark=NAVIGATE, closed_loop=True)] == \
        [k for k in NAV_KEYS if k not in ("mppi_pink_1.0", "mppi_lowpass_1.0", "smppi_2.0", "kmppi_1.0", "cu_mlp",
                                     "cumppi_pipe", "mix_cu_mppi_0.5", "cfu_mppi")]
    assert [m.key for m in parse_methods(None, benchmark=PAPER, closed_loop=True)] == \
        [k for k in closed if k not in PAPER_OPT_IN]
    assert [m.key for m in parse_methods(None, benchmark=PAPER, closed_loop=False)] == \
        [k for k in opened if k not in PAPER_OPT_IN]
    assert gaussian_baselines(NAVIGATE) == ("mppi_0.1", "mppi_0.3", "mppi_1.0")


def test_a_shared_method_is_one_object_with_each_benchmarks_label():
    paper, nav = methods_of(PAPER), methods_of(NAVIGATE)
    for key in SHARED:
        assert paper[key] is nav[key] is METHODS[key], key
        got = {b: parse_methods([key], benchmark=b, closed_loop=True)[0] for b in BENCHMARKS}
        assert got[PAPER] is got[NAVIGATE] is METHODS[key], key
    assert {k: m.label_in(NAVIGATE) for k, m in nav.items()} == NAV_LABELS
    assert {k: paper[k].label_in(PAPER) for k in PAPER_LABELS} == PAPER_LABELS
    assert all(paper[k].label == PAPER_LABELS[k] for k in PAPER_LABELS)  # the paper's figures print .label


@pytest.mark.parametrize("keys,where,closed_loop,message", [
    (["mppi_1.0", "magic"], NAVIGATE, True, "unknown method(s) magic; choose from mppi_0.1, mppi_0.3, mppi_1.0, "
     "log_mppi_0.3, mppi_pink_1.0, mppi_lowpass_1.0, smppi_2.0, kmppi_1.0, uniform, cu_table, cu_coverage, cu_mlp, "
     "cumppi, cumppi_pipe, mix_cu_mppi_0.5, cfu_mppi"),
    (["mppi_low"], NAVIGATE, True, "unknown method(s) mppi_low; choose from mppi_0.1"),  # the paper's key
    (["mppi_0.3", "cfu_mppi"], PAPER, True, "unknown method(s) mppi_0.3, cfu_mppi; choose from mppi_low"),
    (["cumppi"], PAPER, False, "unknown method(s) cumppi; choose from"),  # closed-loop only
    (["cu_graph"], PAPER, True, "unknown method(s) cu_graph; choose from"),  # open-loop only
    (["cu_table", "uniform", "cu_table"], NAVIGATE, True, "a method is named twice"),
    (["mppi_low", "mppi_low"], PAPER, False, "a method is named twice"),
    (["cu_table"], "paper_v2", True, "unknown benchmark 'paper_v2'; choose from paper, navigate"),
])
def test_a_wrong_key_is_refused_with_one_error(keys, where, closed_loop, message):
    with pytest.raises(ValueError) as err:
        parse_methods(keys, benchmark=where, closed_loop=closed_loop)
    assert message in str(err.value)


@pytest.mark.parametrize("kw,message", [
    ({}, "give the benchmark(s) it belongs to"),
    ({"benchmarks": ("nav",)}, "benchmarks names 'nav'"),
    ({"benchmarks": (PAPER,), "labels": ((NAVIGATE, "x"),)}, "labels names 'navigate', not one of its benchmarks"),
    ({"benchmarks": (NAVIGATE,), "opt_in": (PAPER,)}, "opt_in names 'paper'"),
])
def test_a_method_entry_names_only_known_benchmarks(kw, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Method("x", "x", "mppi", MPPI, GaussianSampler, 0.1, **kw)


def test_an_added_entry_shows_in_its_benchmark_only(monkeypatch):
    monkeypatch.setitem(METHODS, "extra", Method("extra", "an extra", "mppi", MPPI, GaussianSampler, 0.5,
                                                 benchmarks=(NAVIGATE,)))
    assert "extra" in methods_of(NAVIGATE) and "extra" not in methods_of(PAPER)
    assert parse_methods(["extra"], benchmark=NAVIGATE, closed_loop=True)[0] is METHODS["extra"]
    with pytest.raises(ValueError, match="unknown method"):
        parse_methods(["extra"], benchmark=PAPER, closed_loop=True)

"""Fixed parameters of the evaluation and the paper's published numbers, in one place.

Everything an experiment needs to be rerun with the same numbers lives here (file paths: :mod:`eval.common.paths`):
noise levels, the MPPI temperature, and the values printed beside ours ("paper" columns). The paper is *C-Uniform Trajectory
Sampling for Fast Motion Planning* (Poyrazoglu, Cao, Isler); its Tables I-III are copied below verbatim.
"""

from __future__ import annotations

LAMBDA = 0.567
"""MPPI temperature of every controller and weighting (the paper's lambda)"""
DT = 0.2
"""time step of the Dubins preset (s)"""
NOISE_LEVELS = {"low": 0.03, "medium": 0.1, "high": 0.3}
"""standard deviation of the Gaussian / normal-log-normal noise (rad/s), the paper's Sigma = 0.03 / 0.1 / 0.3"""

PAPER_COVERAGE = {  # Table I: N -> method -> distinct cells (2 s trajectories)
    250: {"mppi_low": 21, "mppi_medium": 86, "mppi_high": 329, "log_mppi_low": 74, "log_mppi_medium": 271,
          "log_mppi_high": 674, "cu_graph": 737},
    500: {"mppi_low": 23, "mppi_medium": 94, "mppi_high": 356, "log_mppi_low": 79, "log_mppi_medium": 345,
          "log_mppi_high": 897, "cu_graph": 995},
    1000: {"mppi_low": 26, "mppi_medium": 103, "mppi_high": 410, "log_mppi_low": 76, "log_mppi_medium": 390,
           "log_mppi_high": 1140, "cu_graph": 1382},
    2500: {"mppi_low": 28, "mppi_medium": 112, "mppi_high": 529, "log_mppi_low": 93, "log_mppi_medium": 470,
           "log_mppi_high": 1420, "cu_graph": 1851},
    5000: {"mppi_low": 27, "mppi_medium": 120, "mppi_high": 584, "log_mppi_low": 100, "log_mppi_medium": 525,
           "log_mppi_high": 1637, "cu_graph": 2271},
    10000: {"mppi_low": 29, "mppi_medium": 131, "mppi_high": 653, "log_mppi_low": 104, "log_mppi_medium": 568,
            "log_mppi_high": 1838, "cu_graph": 2578},
}
PAPER_COVERAGE_NOTE = ("the paper's C-Uniform column comes from sampling cell sequences on the flow graph "
                       "(cu_graph), not from executed rollouts; its MPPI columns do not say which noise law "
                       "log-MPPI used beyond Sigma")

PAPER_SUDDEN_OBSTACLE = {  # Table II: appearance time (s; 0 = fully visible) -> family -> N -> success rate
    0.0: {"mppi": {500: 1.0, 1000: 1.0}, "log_mppi": {500: 1.0, 1000: 1.0}, "cuniform": {500: 1.0, 1000: 1.0}},
    0.2: {"mppi": {500: 1.0, 1000: 1.0}, "log_mppi": {500: 1.0, 1000: 1.0}, "cuniform": {500: 1.0, 1000: 1.0}},
    0.5: {"mppi": {500: 0.55, 1000: 0.85}, "log_mppi": {500: 0.95, 1000: 0.95}, "cuniform": {500: 1.0, 1000: 1.0}},
    0.8: {"mppi": {500: 0.3, 1000: 0.35}, "log_mppi": {500: 0.45, 1000: 0.40}, "cuniform": {500: 0.7, 1000: 0.65}},
    1.0: {"mppi": {500: 0.05, 1000: 0.15}, "log_mppi": {500: 0.15, 1000: 0.25}, "cuniform": {500: 0.25, 1000: 0.25}},
}

PAPER_CLUTTERED = {  # Table III: environment -> family -> N -> success rate (10 start poses)
    "u_shape": {"mppi": {500: 0.1, 1000: 0.1, 2500: 0.1}, "log_mppi": {500: 0.1, 1000: 0.1, 2500: 0.1},
                "cuniform": {500: 0.8, 1000: 0.8, 2500: 0.8}},
    "rectangles": {"mppi": {500: 0.1, 1000: 0.3, 2500: 0.3}, "log_mppi": {500: 0.4, 1000: 0.6, 2500: 0.8},
                   "cuniform": {500: 1.0, 1000: 1.0, 2500: 1.0}},
}

"""The coverage method: tables that make real rollouts cover the reachable cells (reachable states, exact propagation and its adjoint)."""

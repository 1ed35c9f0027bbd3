"""The paper's experiments: coverage (Table I), uniformity, sudden obstacle (Table II), cluttered (Table III)."""

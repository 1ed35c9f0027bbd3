"""What every experiment shares: the method registry, parameters, output paths, statistics, markdown tables, figures."""

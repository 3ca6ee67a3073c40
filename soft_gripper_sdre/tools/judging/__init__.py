"""Tools that judge results: law comparisons, robustness, sweeps, reports of recorded runs."""

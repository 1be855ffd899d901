"""Studies: groups of runs and their summaries (`service`), and the cached exploration reports
and robustness maps of stored controllers (`evaluation`)."""

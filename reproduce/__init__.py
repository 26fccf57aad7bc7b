"""``swarm reproduce``: the paper's Tables 1-4 as data (spec), one resumable Ray task
per (cell, seed) (cells, runner), and the tables rendered from the results (tables)."""

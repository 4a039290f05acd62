"""Standing benchmarks: each measures one thing and prints its figures and ratios in one run.

Figures of retired one-off (before/after) runs, and hand-recorded runs of these, are in
``docs/HISTORY.md``; ``local.py`` is the benchmarks' helper, not a benchmark.
"""

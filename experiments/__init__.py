"""One-off experiments and recipe runs: ``python -m experiments.<name>`` from the repository root.

Each trains or compares recipes (a training budget, a precision, a share of scenes, the shipped models) rather than
measuring the product, which ``bench/`` does. Their numbers go where the benchmarks' go, ``bench/results/``.
"""

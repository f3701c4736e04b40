"""Measurements of the product that save numbers (never timed tests): ``python -m bench.<name>`` from the repository
root.

Each writes ``bench/results/<name>.json`` (with the machine and library versions)
and a markdown table beside it; findings written by hand live in
``bench/results/*.md`` too, and docstrings link there instead of quoting numbers.
Experiments that train recipes to compare are in ``experiments/``, fuzzers and shared helpers in ``tools/``.
"""

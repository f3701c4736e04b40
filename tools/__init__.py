"""Code that bench, experiments and tests share, and the fuzzers: ``python -m tools.<name>`` from the repository root.

Nothing here measures the product (that is ``bench/``) or trains a recipe to compare (``experiments/``); tests
import from here and never from those two, so that a benchmark or an experiment can change without breaking a test.
Imports go one way: experiments may import bench and tools, bench may import tools, tools imports neither.
"""

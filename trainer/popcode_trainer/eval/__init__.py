"""Evaluation: BOP pose errors, recall scores and tables, results files and figures."""

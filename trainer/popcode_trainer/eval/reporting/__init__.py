"""Evaluation results -> tables (markdown, JSON), BOP19 results CSV and figures."""

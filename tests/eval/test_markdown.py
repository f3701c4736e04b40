"""The one markdown-table writer."""

from popcode_trainer.eval.reporting.markdown import markdown_table


def test_markdown_table_has_a_header_rule_and_one_line_per_row() -> None:
    text = markdown_table(["a", "b"], [(1, "x"), ("2.50", None)])
    assert text.split("\n") == ["| a | b |", "|---|---|", "| 1 | x |", "| 2.50 | None |"]


def test_markdown_table_without_rows_is_the_header_alone() -> None:
    assert markdown_table(["only"], []) == "| only |\n|---|"

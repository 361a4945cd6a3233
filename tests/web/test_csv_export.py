"""The history's CSV export never hands a spreadsheet a formula."""

from trimeter.web.history_routes import _spreadsheet_safe


def test_text_cells_that_a_spreadsheet_would_evaluate_are_quoted_and_numbers_are_not():
    assert _spreadsheet_safe('=HYPERLINK("http://x")') == '\'=HYPERLINK("http://x")'
    assert [_spreadsheet_safe(v) for v in ("+1", "-cmd", "@SUM(A1)")] == ["'+1", "'-cmd", "'@SUM(A1)"]
    assert _spreadsheet_safe("cyan-ink") == "cyan-ink"
    assert _spreadsheet_safe(-0.5) == -0.5 and _spreadsheet_safe(None) == ""

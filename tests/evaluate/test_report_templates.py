"""The benchmark report is rendered from Jinja2 templates shipped as package data; HTML is escaped."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

pytest.importorskip("jinja2")


def _rows():
    from .test_charts import _row
    rows = []
    for i, (label, ds) in enumerate((("a<b>&c|d", "HDR:x"), ("cf", "HDR:x"), ("cf", "HDR:x"))):
        r = _row(label, "akf" if i == 0 else "cf", 1.0 + i, 0.01 * (1 + i), 0.8 - 0.1 * i, ds=ds, q=math.nan)
        r.update(task=i, run=0)
        rows.append(r)
    rows[2]["status"] = "error: ValueError: give `--weights-e2vid PATH` <here> & there"
    return rows


def test_html_escaped_and_markdown_raw(tmp_path):
    from hybridhdr.evaluate.report import write_report
    w = write_report(_rows(), tmp_path, None, charts=False)
    html = w["report_html"].read_text(encoding="utf-8")
    md = w["report_md"].read_text(encoding="utf-8")
    assert html.startswith("<!DOCTYPE html>") and html.rstrip().endswith("</html>")
    # the method name is data: escaped in HTML, never markup
    assert "a&lt;b&gt;&amp;c|d" in html and "a<b>" not in html
    assert "<here>" not in html and "&lt;here&gt; &amp; there" in html
    # Markdown marks become markup: no literal backticks or ** in the HTML
    assert "`" not in html and "**" not in html
    assert "<code>--weights-e2vid PATH</code>" in html
    # the Markdown keeps the text; a '|' in a cell is escaped so the table keeps its columns
    assert "| HDR:x | a<b>&c\\|d |" in md
    header = next(ln for ln in md.splitlines() if ln.startswith("| dataset | method |"))
    row = next(ln for ln in md.splitlines() if ln.startswith("| HDR:x | a<b>"))
    assert len(re.split(r"(?<!\\)\|", header)) == len(re.split(r"(?<!\\)\|", row))
    assert "- HDR:x / cf: error: ValueError: give `--weights-e2vid PATH` <here> & there" in md
    # the HTML table has as many cells per row as header cells
    table = html.split("<h2>Results</h2>", 1)[1].split("</table>", 1)[0]
    n_th = table.count("<th>")
    for tr in re.findall(r"<tr>(.*?)</tr>", table.split("<tbody>", 1)[1]):
        assert tr.count("<td>") == n_th


def test_templates_are_package_data_and_no_markup_in_code():
    import importlib.resources

    import hybridhdr.evaluate.report as R
    tdir = importlib.resources.files("hybridhdr.evaluate") / "templates"
    for name in ("report.html.j2", "report.md.j2"):
        assert (tdir / name).is_file()
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    py = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    assert "templates/*.j2" in py["tool"]["setuptools"]["package-data"]["hybridhdr.evaluate"]
    assert any(d.lower().startswith("jinja2") for d in py["project"]["optional-dependencies"]["images"])
    # the module builds no HTML tags itself: all markup lives in the templates
    src = Path(R.__file__).read_text(encoding="utf-8")
    assert not re.search(r"<(table|tr|td|th|h1|h2|p|img|html|b|code)[ >]", src)


def test_format_table_and_akf_text_through_the_templates():
    from hybridhdr.evaluate.report import akf_vs_cf_parts, akf_vs_cf_text, format_table
    assert format_table(["a", "b"], [[1, 2], [3, "x|y"]]) == "| a | b |\n|---|---|\n| 1 | 2 |\n| 3 | x\\|y |"
    assert format_table(["a"], []) == "| a |\n|---|"
    c = {"datasets": ["d"], "akf_mse": 0.01, "cf_mse": 0.02, "mse_reduction_pct": 50.0, "akf_ssim": 0.8,
         "cf_ssim": 0.7, "ssim_improvement_pct": 14.3, "akf_log_mse": 0.1, "cf_log_mse": 0.2,
         "log_mse_reduction_pct": 50.0, "akf_log_ssim": 0.9, "cf_log_ssim": 0.8, "log_ssim_improvement_pct": 12.5}
    text = akf_vs_cf_text(c)
    assert "(**AKF MSE 50.0% lower**; paper: 48% lower)" in text and "(**+14.3% SSIM**; paper: +11%)" in text
    assert [p["style"] for p in akf_vs_cf_parts(c)].count("b") == 2

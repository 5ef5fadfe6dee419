"""The demo's headline figures: one block, each figure naming its set and scoring (figures from
different sets and scorings must not read as comparable)."""

from hybridhdr.evaluate.paper import headline_lines


def test_headline_names_set_and_scoring_of_every_figure():
    cmp_ = {"datasets": ["hdr_disc"], "mse_reduction_pct": 96.0, "log_mse_reduction_pct": 76.5}
    rows = [{"method_label": "akf", "status": "ok", "normalise": "none"},
            {"method_label": "cf", "status": "ok", "normalise": "none"}]
    paper = {"mse_reduction_pct": 44.2, "log_mse_reduction_pct": 63.4, "ahdr_mse_reduction_pct": -5.0}
    lines = headline_lines(cmp_, rows, paper)
    text = "\n".join(lines)
    assert lines[0].startswith("Headline figures")
    figures = [x for x in lines if "AKF" in x and "%" in x]
    assert len(figures) == 4  # bench linear, bench log, Table 1 HDR, Table 1 AHDR
    for x in figures:
        assert "set" in x and ("MSE" in x or "log intensity" in x), x
    assert "96.0% lower" in text and "76.5% lower" in text and "44.2% lower" in text and "5.0% higher" in text
    assert "hdr_disc" in text and "HDR set" in text and "AHDR set" in text
    assert headline_lines(None, [], {})[0].startswith("Headline figures")  # nothing measured: no figure

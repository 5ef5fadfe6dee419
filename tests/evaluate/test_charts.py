"""Speed–accuracy and stability charts: Pareto front, failure points, numerical-failure counts."""

import math

import pytest

from hybridhdr.evaluate import charts as C


def _row(label, method, t, mse, ssim, ds="d", status="ok", nonfinite=0, **kw):
    return {"dataset": ds, "method_label": label, "method_name": label.split(" [")[0], "method": method,
            "time_per_data_s": t, "mse": mse, "ssim": ssim, "status": status, "n_nonfinite": nonfinite, **kw}


def test_pareto_front_by_hand():
    pts = [{"x": 1.0, "y": 0.5}, {"x": 2.0, "y": 0.4}, {"x": 3.0, "y": 0.1}, {"x": 0.5, "y": 0.9},
           {"x": 4.0, "y": 0.2}, {"x": math.nan, "y": 0.0}]
    # lower is better: 0.5->0.9, 1->0.5, 2->0.4, 3->0.1 each improve; 4->0.2 does not
    assert C.pareto_front(pts, True) == [3, 0, 1, 2]
    # higher is better: 0.5->0.9 only
    assert C.pareto_front(pts, False) == [3]


def test_speed_accuracy_points_average_and_failures():
    rows = [_row("akf", "akf", 1.0, 0.1, 0.8), _row("akf", "akf", 3.0, 0.3, 0.6, ds="e"),
            _row("cf", "cf", 0.5, 0.2, 0.7), _row("cf", "cf", 0.5, 0.2, 0.7, status="error: x")]
    pts = C.speed_accuracy_points(rows, "mse")
    assert pts[0] == {"label": "akf", "method": "akf", "x": 2.0, "y": pytest.approx(0.2), "n": 2, "n_failed": 0}
    assert pts[1]["n_failed"] == 1 and pts[1]["x"] == 0.5
    assert C.speed_accuracy_points(rows, "mse", datasets=["e"])[0]["x"] == 3.0


def test_stability_failure_point_rules():
    rows = []
    for x, ssim, nf, st in ((0, 0.9, 0, "ok"), (1, 0.85, 0, "ok"), (2, 0.6, 0, "ok"), (3, 0.3, 0, "ok")):
        rows.append(_row("akf", "akf", 1, 0.1, ssim, nonfinite=nf, status=st, **{"ds.noise": x}))
    for x, ssim, nf, st in ((0, 0.9, 0, "ok"), (1, 0.9, 5, "ok"), (2, math.nan, 0, "ok"), (3, 0.1, 0, "error: boom")):
        rows.append(_row("bad", "cf", 1, 0.1, ssim, nonfinite=nf, status=st, **{"ds.noise": x}))
    cur = C.stability_curves(rows, dataset="d", axis="noise", metric="ssim", bound=0.7)
    assert cur["akf"]["failed_at"] == 2 and "0.6 < bound 0.7" in cur["akf"]["reason"]
    assert cur["bad"]["failed_at"] == 1 and "5 NaN/Inf" in cur["bad"]["reason"]
    rel = C.stability_curves(rows, dataset="d", axis="noise", metric="ssim", relative_bound=0.5)
    assert rel["akf"]["failed_at"] == 3 and rel["akf"]["bound"] == pytest.approx(0.45)
    # decreasing stress: the sweep is read from the largest value down
    dec = C.stability_curves(rows, dataset="d", axis="noise", metric="ssim", bound=0.7, stress="decreasing")
    assert dec["akf"]["failed_at"] == 3
    assert dec["bad"]["failed_at"] == 3 and "error" in dec["bad"]["reason"]
    none = C.stability_curves(rows, dataset="d", axis="noise", metric="ssim", bound=0.0)
    assert none["akf"]["failed_at"] is None


def test_numerical_failures_counts():
    rows = [_row("a", "akf", 1, 0.1, 0.9), _row("a", "akf", 1, 0.1, 0.9, nonfinite=7),
            _row("c", "cf", 1, 0.1, 0.9, status="error: x")]
    nf = {n["method"]: n for n in C.numerical_failures(rows)}
    assert nf["akf"] == {"method": "akf", "runs": 2, "runs_with_nonfinite": 1, "nonfinite_pixels": 7, "errors": 0}
    assert nf["cf"]["errors"] == 1


def test_plots_return_fig_ax(tmp_path):
    rows = [_row("akf", "akf", 1.0, 0.1, 0.8, **{"ds.noise": 0}), _row("cf", "cf", 0.5, 0.2, 0.7, **{"ds.noise": 0}),
            _row("akf", "akf", 1.0, 0.3, 0.5, **{"ds.noise": 10}), _row("cf", "cf", 0.5, 0.2, 0.7, **{"ds.noise": 10})]
    fig, ax = C.plot_speed_accuracy(rows, "mse")
    assert ax.get_xlabel().startswith("wall time per second")
    assert any(t.get_text() == "Pareto front" for t in ax.get_legend().get_texts())
    fig.savefig(tmp_path / "sa.png")
    fig2, ax2 = C.plot_stability(rows, dataset="d", axis="noise", metric="ssim", bound=0.6)
    # one red failure cross for akf (0.5 < 0.6 at noise 10)
    crosses = [ln for ln in ax2.get_lines() if ln.get_marker() == "x" and len(ln.get_xdata()) == 1]
    assert len(crosses) == 1 and list(crosses[0].get_xdata()) == [10]
    import matplotlib.pyplot as plt
    plt.close(fig)
    plt.close(fig2)


def _chart_rows():
    rows = []
    for label, method, t, base in (("akf", "akf", 1.0, 0.9), ("cf", "cf", 0.3, 0.8), ("edi", "edi", 2.0, 0.7)):
        for x in (0, 1, 2, 3):
            ssim = base - 0.2 * x
            rows.append(_row(label, method, t * (1 + 0.1 * x), 0.01 * (1 + x), ssim, ds="HDR:dark_room_window",
                             nonfinite=0, q=math.nan, **{"ds.noise": x}))
    return rows


def _assert_no_legend_overlap_and_no_empty_panel(fig):
    """Every visible axes has data; no legend box intersects any axes' plotting area."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    axes = [a for a in fig.axes if a.get_visible() and a.axison]
    for a in axes:
        assert a.lines or a.collections, f"empty panel: {a.get_title()!r}"
    for a in fig.axes:
        leg = a.get_legend()
        if leg is None:
            continue
        lb = leg.get_window_extent(r)
        for b in axes:
            assert not lb.overlaps(b.get_window_extent(r)), (a.get_title(), b.get_title())
        fb = fig.bbox
        assert lb.x0 >= fb.x0 - 1 and lb.x1 <= fb.x1 + 1, "legend runs off the figure"


def test_charts_render_without_legend_overlap_or_empty_panel(tmp_path):
    from hybridhdr.evaluate.report import write_charts
    rows = _chart_rows()
    cfg = {"speed_accuracy": {"metrics": ["mse", "ssim", "q"]},
           "stability": [{"dataset": "HDR:dark_room_window", "axis": "noise", "metric": "ssim", "bound": 0.4},
                         {"dataset": "HDR:dark_room_window", "axis": "noise", "metric": "mse"}]}
    plt = C._plt()
    figs = []
    orig_close = plt.close
    plt.close = lambda fig=None: figs.append(fig)  # keep the figures to inspect them
    try:
        paths, _ = write_charts(rows, tmp_path, cfg)
    finally:
        plt.close = orig_close
    assert set(paths) == {"speed_accuracy", "stability"}
    sa = [f for f in figs if f is not None][0]
    assert len(sa.axes) == 2  # the HDR-VDP Q panel has no data: not drawn
    for fig in figs:
        if fig is not None:
            _assert_no_legend_overlap_and_no_empty_panel(fig)
            orig_close(fig)


def test_results_csv_unique_columns_and_safe_strip_names(tmp_path):
    import csv

    import numpy as np

    from hybridhdr.evaluate import bench as B
    from hybridhdr.evaluate.report import _md_inline_html, safe_file_stem
    rows = _chart_rows()[:2]
    for i, r in enumerate(rows):
        r.update(task=i, run=0, dataset_load_s=0.1, dataset_time_per_data_s=0.2)
    rows[0]["_strip"] = {"LDR": np.zeros((8, 8)), "akf": np.ones((8, 8)), "reference": np.ones((8, 8))}
    w = B.write_results(rows, tmp_path, None, charts=False)
    with open(w["csv"], newline="", encoding="utf-8") as f:
        header = next(csv.reader(f))
    assert len(header) == len(set(header)), [c for c in header if header.count(c) > 1]
    assert header.count("dataset_load_s") == 1
    assert [p.name for p in w["strips"]] == ["strip_000_HDR_dark_room_window.png"]
    assert safe_file_stem("a:b/c d") == "a_b_c_d"
    html_text = (tmp_path / "report.html").read_text()
    assert "`" not in html_text
    assert _md_inline_html("use `x < y` and **b**") == "use <code>x &lt; y</code> and <b>b</b>"


@pytest.mark.parametrize("span", [1.1, 1.6, 3.0])
def test_speed_accuracy_tick_labels_do_not_collide(span):
    """Log time axes spanning about a decade: matplotlib's minor labels (2, 3, 4, 6) ran together
    on the quarter-width panels of speed_accuracy.png."""
    plt = C._plt()
    rows = []
    for i, (label, base) in enumerate((("akf", 0.9), ("cf", 0.8), ("hpf", 0.7), ("frames", 0.6))):
        rows.append(_row(label, label, 0.0125 * 10 ** (span * i / 3), 0.01 * (i + 1), base))
    fig, axes = plt.subplots(1, 4, figsize=(22.4, 4.4), squeeze=False)
    try:
        for ax, m in zip(axes[0], ("mse", "ssim", "mse", "ssim")):
            C.plot_speed_accuracy(rows, m, ax=ax)
        fig.canvas.draw()
        r = fig.canvas.get_renderer()
        for ax in axes[0]:
            for axis in (ax.xaxis, ax.yaxis):
                ticks = [t for t in axis.get_majorticklabels() + axis.get_minorticklabels()
                         if t.get_visible() and t.get_text()]
                lo, hi = sorted(axis.get_view_interval())
                inside = [t for t in ticks if lo <= (t.get_position()[0] if axis is ax.xaxis
                                                     else t.get_position()[1]) <= hi]
                assert inside, "no tick label at all"
                boxes = [t.get_window_extent(r) for t in inside]
                for i in range(len(boxes)):
                    for j in range(i + 1, len(boxes)):
                        assert not boxes[i].overlaps(boxes[j]), (inside[i].get_text(), inside[j].get_text())
    finally:
        plt.close(fig)

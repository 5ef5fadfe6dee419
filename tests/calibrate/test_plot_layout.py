"""Calibration charts read well: titles inside the figure, legends off the curves, every curve visible,
panels titled with their own image."""

from __future__ import annotations

import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _assert_titles_fit(fig):
    """Each axes title lies inside the figure and no two titles overlap."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    fb = fig.bbox
    boxes = []
    for a in fig.axes:
        for t in (a.title, a._left_title, a._right_title):
            if not t.get_text():
                continue
            b = t.get_window_extent(r)
            assert b.x0 >= fb.x0 - 0.5 and b.x1 <= fb.x1 + 0.5 and b.y0 >= fb.y0 - 0.5 and b.y1 <= fb.y1 + 0.5, \
                f"title {t.get_text()!r} runs off the figure: {b} outside {fb}"
            boxes.append((t.get_text(), b))
    for i, (ti, bi) in enumerate(boxes):
        for tj, bj in boxes[i + 1:]:
            assert not bi.overlaps(bj), (ti, tj)


def _assert_legends_clear_of_curves(fig):
    """No legend box covers a point of any curve (lines sampled densely in display space)."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    for a in fig.axes:
        leg = a.get_legend()
        if leg is None:
            continue
        lb = leg.get_window_extent(r)
        for ln in a.get_lines():
            path = ln.get_transform().transform_path(ln.get_path().interpolated(40))
            xy = path.vertices
            inside = (xy[:, 0] > lb.x0) & (xy[:, 0] < lb.x1) & (xy[:, 1] > lb.y0) & (xy[:, 1] < lb.y1)
            assert not inside.any(), f"legend of {a.get_title()!r} covers {ln.get_label()!r}"


def _pixels(fig):
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(np.int16)


def _visible_pixels(fig, line) -> int:
    """Pixels drawn in ``line``'s own colour that change when it is hidden: how much of it shows over
    everything drawn on top (a curve covered by another keeps only anti-aliased fringes of mixed colour)."""
    from matplotlib.colors import to_rgba
    r, g, b, alpha = to_rgba(line.get_color(), line.get_alpha())
    colour = 255 * (alpha * np.array([r, g, b]) + (1 - alpha))  # over the white axes background
    with_line = _pixels(fig)
    line.set_visible(False)
    try:
        without = _pixels(fig)
    finally:
        line.set_visible(True)
    changed = np.abs(with_line - without).sum(axis=-1) > 30
    own = np.abs(with_line - colour).sum(axis=-1) < 60
    return int((changed & own).sum())


def test_crf_profile_titles_fit_and_no_legend_on_curves(tmp_path, monkeypatch):
    from hybridhdr.calibrate.crf import debevec
    from hybridhdr.calibrate.noise_profile import estimate_sigma2_im, noise_profile, plot_profile

    from .test_noise_profile import _noisy_brackets
    ex = np.array([1 / 16, 1 / 4, 1.0, 4.0])
    imgs = _noisy_brackets(0.5, ex)
    crf = debevec(imgs, ex)
    s2, _ = estimate_sigma2_im(imgs, ex, crf)
    prof = noise_profile(crf, sigma2_im=s2, floor=0.09, name="synthetic gamma")
    figs = []
    real_close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figs.append(fig))
    plot_profile(crf, prof, tmp_path / "crf_profile.png")
    monkeypatch.setattr(plt, "close", real_close)
    (fig,) = figs
    try:
        assert len(fig.axes) == 3
        _assert_titles_fit(fig)
        _assert_legends_clear_of_curves(fig)
        assert "0.09" in fig.axes[1].get_title()  # the floor is named
        assert f"{s2:.3g}" in fig.axes[2].get_title()
    finally:
        real_close(fig)


def test_rig_charts_on_the_opencv_stereo_sample(shared_data, tmp_path, monkeypatch):
    """``calibrate rig --left/--right``: right panels named by the right images; parallax max visible."""
    from hybridhdr.calibrate import _cli_rig
    from hybridhdr.cli import main

    d = shared_data("checkerboard/opencv_stereo")
    left = sorted(d.glob("left*.jpg"))[:6]
    right = sorted(d.glob("right*.jpg"))[:6]
    figs = {}
    real_save = _cli_rig._save_png

    def keep(fig, path):
        figs[path.name] = fig
        fig.savefig(path, dpi=60)

    monkeypatch.setattr(_cli_rig, "_save_png", keep)
    out = tmp_path / "lr"
    assert main(["calibrate", "rig", "--left", *map(str, left), "--right", *map(str, right), "--board", "9x6",
                 "--square-mm", "25", "--detector-frames", "classic", "--detector-events", "classic",
                 "--prune-factor", "0", "--min-views", "4", "--depth-m", "2", "--out", str(out),
                 "--no-progress"]) == 0
    assert real_save is not keep
    try:
        assert set(figs) == {"corners.png", "per_view_errors.png", "parallax.png"}
        # corners: top row the left images, bottom row the right camera's own images
        cf = figs["corners.png"]
        titles = [a.get_title() for a in cf.axes]
        n = len(titles) // 2
        assert n >= 1
        assert titles[:n] == [f"left {p.stem}" for p in left[:n]]
        assert titles[n:] == [f"right {p.stem}" for p in right[:n]]
        for f in figs.values():
            _assert_titles_fit(f)
            _assert_legends_clear_of_curves(f)
        # parallax: the max curve shows although max and median nearly coincide for a translation
        pf = figs["parallax.png"]
        ax = pf.axes[0]
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        mx, med = lines["max over the image"], lines["median"]
        x0, x1 = sorted(ax.get_xlim())
        y0, y1 = sorted(ax.get_ylim())
        for ln in (mx, med):
            xs, ys = ln.get_data()
            assert np.all((xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)), ln.get_label()
        assert _visible_pixels(pf, mx) > 300
        assert _visible_pixels(pf, med) > 100
    finally:
        for f in figs.values():
            plt.close(f)

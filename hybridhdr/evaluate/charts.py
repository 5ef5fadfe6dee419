"""Speed–accuracy and stability charts from benchmark rows.

Rows are the dicts of :func:`hybridhdr.evaluate.bench.run_bench` (or the rows of
``results.csv`` read back with :func:`hybridhdr.evaluate.bench.read_results`).

- :func:`speed_accuracy_points` / :func:`plot_speed_accuracy`: one point per method setting
  (``method_label``: method plus its grid values, e.g. AKF with augmentation or deblurring off),
  x = wall time per second of data (s/s, log axis), y = MSE, SSIM, JOD or Q, averaged over the chosen
  datasets; the Pareto front (no other point both faster and better) is drawn as a step line
  and its points ringed.
- :func:`stability_curves` / :func:`plot_stability`: metric against a stress value per method,
  the **failure point** marked: the first stress value (in order of increasing stress) where
  the metric is past the stated bound, or non-finite pixels appeared, or the metric is NaN, or
  the run failed.
- :func:`numerical_failures`: per method, runs with NaN/Inf pixels and the total count.

Plot functions follow the project convention: ``plot_*(..., ax=None) -> (fig, ax)``, matplotlib
imported inside, never ``plt.show()``.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np

__all__ = ["LOWER_IS_BETTER", "speed_accuracy_points", "pareto_front", "plot_speed_accuracy",
           "stability_curves", "plot_stability", "numerical_failures", "stress_value"]

LOWER_IS_BETTER = {"mse": True, "psnr_db": False, "ssim": False, "global_ssim": False, "pu_psnr_db": False,
                   "pu_ssim": False, "q": False, "log_mse": True, "log_ssim": False, "jod": False}
_LABELS = {"mse": "MSE (linear, [0, 1])", "ssim": "SSIM (σ = 1.5)", "q": "HDR-VDP Q", "psnr_db": "PSNR (dB)",
           "pu_ssim": "PU21-SSIM", "pu_psnr_db": "PU21-PSNR (dB)", "global_ssim": "global SSIM (EAF)",
           "log_mse": "MSE (log intensity, [0, 1])", "log_ssim": "SSIM (log intensity)",
           "jod": "ColorVideoVDP JOD (10 = identical)"}


def _plt():
    try:
        import matplotlib
        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover
        raise ImportError("charts need matplotlib (pip install 'hybridhdr[images]')") from e
    return plt


def _f(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _ok(r) -> bool:
    return str(r.get("status", "")) == "ok"


def _not_computed(r, metric: str) -> str:
    """Why an ok row has no ``metric`` by design (its package is not installed: JOD without
    cvvdp/PyTorch), else ''. Such points are n/a, not failures."""
    from .metrics import JOD_NA
    note = str(r.get(f"{metric}_note") or "") if _ok(r) else ""
    return note if note == JOD_NA else ""


def outside_legend(ax, **kw):
    """Legend below the axes, outside the plotting area, so it never covers data or failure
    markers (``loc="best"`` did); callers' ``tight_layout`` / ``bbox_inches="tight"`` make room."""
    handles, labels = ax.get_legend_handles_labels()
    if not handles:
        return None
    opts = dict(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=min(3, len(handles)),
                frameon=False)
    opts.update(kw)
    return ax.legend(handles, labels, **opts)


def speed_accuracy_points(rows, metric: str, datasets=None, *, group_by: str = "method_label",
                          time_column: str = "time_per_data_s") -> list[dict]:
    """Mean (time per second of data, metric) per group over ok runs of ``datasets``.

    ``group_by="method_label"`` (one point per method setting, time = reconstruction) or
    ``"dataset_variant"`` with ``time_column="dataset_time_per_data_s"`` (one point per
    simulator setting, e.g. adaptive vs fixed sampling, time = simulation).
    """
    groups: "OrderedDict[str, list]" = OrderedDict()
    for r in rows:
        if datasets is not None and r.get("dataset") not in datasets:
            continue
        groups.setdefault(r.get(group_by), []).append(r)
    pts = []
    for label, rs in groups.items():
        good = [r for r in rs if _ok(r)]
        xs = [_f(r.get(time_column)) for r in good]
        ys = [_f(r.get(metric)) for r in good]
        pts.append({"label": label, "method": rs[0].get("method") if group_by == "method_label" else rs[0].get("dataset"), "x": float(np.mean(xs)) if xs else math.nan,
                    "y": float(np.mean(ys)) if ys else math.nan, "n": len(good), "n_failed": len(rs) - len(good)})
    return pts


def sparse_minor_log_labels(axis) -> None:
    """Label a log axis's minor ticks at 2 and 5 only, and only when it spans under two decades.

    matplotlib labels the minor ticks 2, 3, 4 and 6 of an axis spanning about one decade; on a
    panel a quarter of a figure wide those labels run into each other."""
    from matplotlib.ticker import FuncFormatter

    def fmt(x, pos=None):
        lo, hi = sorted(axis.get_view_interval())
        if not (x > 0 and lo > 0 and hi / lo < 100):
            return ""
        e = math.floor(math.log10(x) + 1e-9)
        m = x / 10.0 ** e
        if abs(m - round(m)) > 1e-6 or round(m) not in (2, 5):
            return ""
        return f"${int(round(m))}\\times10^{{{e}}}$"
    axis.set_minor_formatter(FuncFormatter(fmt))


def pareto_front(points, lower_is_better: bool) -> list[int]:
    """Indices of the points no other point beats in both time (lower) and metric; by time."""
    idx = [i for i, p in enumerate(points) if math.isfinite(p["x"]) and math.isfinite(p["y"])]
    sgn = 1.0 if lower_is_better else -1.0
    idx.sort(key=lambda i: (points[i]["x"], sgn * points[i]["y"]))
    front, best = [], math.inf
    for i in idx:
        v = sgn * points[i]["y"]
        if v < best:
            front.append(i)
            best = v
    return front


def plot_speed_accuracy(rows, metric: str = "ssim", datasets=None, ax=None, title: str | None = None, *,
                        group_by: str = "method_label", time_column: str = "time_per_data_s",
                        xlabel: str | None = None):
    """Speed–accuracy scatter for one metric with its Pareto front; returns (fig, ax)."""
    plt = _plt()
    if ax is None:
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
    else:
        fig = ax.figure
    pts = speed_accuracy_points(rows, metric, datasets, group_by=group_by, time_column=time_column)
    lower = LOWER_IS_BETTER.get(metric, False)
    methods = sorted({p["method"] for p in pts})
    cmap = plt.get_cmap("tab10")
    colour = {m: cmap(i % 10) for i, m in enumerate(methods)}
    markers = "osD^v<>pP*hX"
    finite = [p for p in pts if math.isfinite(p["x"]) and math.isfinite(p["y"])]
    for i, p in enumerate(pts):
        if not (math.isfinite(p["x"]) and math.isfinite(p["y"])):
            continue
        ax.scatter(p["x"], p["y"], color=colour[p["method"]], marker=markers[i % len(markers)], s=40, zorder=3,
                   label=p["label"])
    front = pareto_front(pts, lower)
    if front:
        fx = [pts[i]["x"] for i in front]
        fy = [pts[i]["y"] for i in front]
        ax.step(fx, fy, where="post", color="0.3", lw=1, ls="--", zorder=2, label="Pareto front")
        ax.scatter(fx, fy, s=140, facecolors="none", edgecolors="k", lw=1.2, zorder=4)
    if finite and all(p["x"] > 0 for p in finite):
        ax.set_xscale("log")
        sparse_minor_log_labels(ax.xaxis)
    if metric == "mse" and finite and all(p["y"] > 0 for p in finite):
        ax.set_yscale("log")
        sparse_minor_log_labels(ax.yaxis)
    ax.set_xlabel(xlabel or "wall time per second of data (s/s, lower = faster)")
    ax.set_ylabel(_LABELS.get(metric, metric) + (" ↓" if lower else " ↑"))
    ax.set_title(title or f"speed–accuracy: {metric}")
    ax.grid(True, which="both", alpha=0.3)
    if not finite:
        ax.text(0.5, 0.5, f"no {metric} values (n/a)", transform=ax.transAxes, ha="center", va="center")
    else:
        outside_legend(ax)
    return fig, ax


def stress_value(row, axis: str) -> float:
    """The stress value of a row: its dataset grid value ``ds.AXIS`` or method grid value ``m.AXIS``."""
    for k in (f"ds.{axis}", f"m.{axis}", axis):
        if k in row and row[k] not in ("", None):
            return _f(row[k])
    return math.nan


def stability_curves(rows, *, dataset: str, axis: str, metric: str = "ssim", bound: float | None = None,
                     better: str | None = None, stress: str = "increasing",
                     relative_bound: float | None = None) -> dict:
    """Per method: stress values, metric values and the failure point.

    Parameters
    ----------
    dataset : str
        Dataset name whose grid holds the stress axis (method-side axes such as
        ``threshold_factor`` are read from the method grid instead).
    axis : str
        Grid key of the stress.
    bound : float, optional
        Failure when the metric is worse than this (above it for MSE, below it for SSIM/Q).
    relative_bound : float, optional
        Failure when the metric is worse than ``relative_bound`` × the method's own value at the
        least-stressed point (e.g. 0.8 for SSIM: a 20 % drop; 2 for MSE: doubled).
    better : {"higher", "lower"}, optional
        Default from the metric (MSE lower, others higher).
    stress : {"increasing", "decreasing"}
        Whether larger axis values are more stress (e.g. noise) or fewer (e.g. exposure scale
        for under-exposure, frame rate).

    Returns
    -------
    dict method_name -> {"x", "y", "nonfinite", "failed_at", "reason"}; points whose metric was
    not computed by design (JOD without PyTorch) are NaN without a failure, and a curve made only
    of them has that note as its ``reason``.
    """
    if stress not in ("increasing", "decreasing"):
        raise ValueError(f"stress must be 'increasing' or 'decreasing', got {stress!r}")
    lower = LOWER_IS_BETTER.get(metric, False) if better is None else (better == "lower")
    if better not in (None, "higher", "lower"):
        raise ValueError(f"better must be 'higher' or 'lower', got {better!r}")
    groups: "OrderedDict[str, list]" = OrderedDict()
    for r in rows:
        if r.get("dataset") != dataset:
            continue
        key = r.get("method_name") or r.get("method_label")
        if f"m.{axis}" not in r:
            key = r.get("method_label")
        groups.setdefault(key, []).append(r)
    out = {}
    for name, rs in groups.items():
        pts = sorted(((stress_value(r, axis), r) for r in rs), key=lambda t: t[0],
                     reverse=(stress == "decreasing"))
        xs, ys, nf = [], [], []
        failed_at, reason = None, ""
        b = bound
        if relative_bound is not None and pts and _ok(pts[0][1]) and math.isfinite(_f(pts[0][1].get(metric))):
            b = relative_bound * _f(pts[0][1].get(metric))
        for x, r in pts:
            y = _f(r.get(metric)) if _ok(r) else math.nan
            n_bad = int(_f(r.get("n_nonfinite")) or 0) if _ok(r) and math.isfinite(_f(r.get("n_nonfinite"))) else 0
            xs.append(x)
            ys.append(y)
            nf.append(n_bad)
            if failed_at is None:
                if not _ok(r):
                    failed_at, reason = x, str(r.get("status", "error"))
                elif n_bad > 0:
                    failed_at, reason = x, f"{n_bad} NaN/Inf pixels"
                elif _not_computed(r, metric):
                    pass
                elif not math.isfinite(y):
                    failed_at, reason = x, f"{metric} is NaN"
                elif b is not None and ((y > b) if lower else (y < b)):
                    how = f"{relative_bound:g}× unstressed = {b:.4g}" if relative_bound is not None else f"{b:g}"
                    failed_at, reason = x, f"{metric} {y:.4g} {'>' if lower else '<'} bound {how}"
        na = {_not_computed(r, metric) for _, r in pts}
        if failed_at is None and len(na) == 1 and "" not in na:
            reason = na.pop()
        out[name] = {"x": xs, "y": ys, "nonfinite": nf, "failed_at": failed_at, "reason": reason, "bound": b}
    return out


def method_colours(names) -> dict:
    """tab10 index per curve name, the same for a method in every panel and chart: the method's
    place in ``reconstruct.METHODS`` (aliases resolved, a grid suffix " [...]" ignored), else a
    fixed digest of the name; a name whose colour is taken in this chart gets the next free one."""
    import zlib

    from ..reconstruct.api import METHOD_ALIASES, METHODS
    order = list(METHODS)
    out, used = {}, set()
    for n in names:
        base = str(n).split(" [")[0]
        base = METHOD_ALIASES.get(base, base)
        k = order.index(base) if base in order else zlib.crc32(base.encode()) % 10
        while k in used and len(used) < 10:
            k = (k + 1) % 10
        used.add(k)
        out[n] = k % 10
    return out


def plot_stability(rows, *, dataset: str, axis: str, metric: str = "ssim", bound: float | None = None,
                   better: str | None = None, stress: str = "increasing", title: str | None = None,
                   log_x: bool | None = None, relative_bound: float | None = None, ax=None):
    """Metric against stress per method, failure points marked with a red ✕; returns (fig, ax)."""
    plt = _plt()
    if ax is None:
        fig, ax = plt.subplots(figsize=(5.6, 4.0))
    else:
        fig = ax.figure
    curves = stability_curves(rows, dataset=dataset, axis=axis, metric=metric, bound=bound, better=better,
                              stress=stress, relative_bound=relative_bound)
    # no curve has a value or a failure: the metric was not computed here (e.g. JOD without PyTorch)
    na = bool(curves) and all(c["failed_at"] is None and not np.isfinite(np.asarray(c["y"], float)).any()
                              for c in curves.values())
    if na and (note := "; ".join(sorted({c["reason"] for c in curves.values()}))):
        ax.text(0.5, 0.5, f"{_LABELS.get(metric, metric)}\n{note}", transform=ax.transAxes, ha="center",
                va="center", fontsize=9, color="0.35")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel(axis)
        ax.set_title(title or f"stability: {axis}", fontsize=9)
        return fig, ax
    cmap = plt.get_cmap("tab10")
    colours = method_colours(list(curves))
    for i, (name, c) in enumerate(curves.items()):
        xs, ys = np.asarray(c["x"], float), np.asarray(c["y"], float)
        order = np.argsort(xs)
        ax.plot(xs[order], ys[order], "o-", color=cmap(colours[name]), ms=4, label=name)
        if c["failed_at"] is not None:
            j = int(np.flatnonzero(xs == c["failed_at"])[0])
            yv = ys[j] if math.isfinite(ys[j]) else np.nanmin(ys) if np.isfinite(ys).any() else 0.0
            ax.plot([c["failed_at"]], [yv], marker="x", color="red", ms=11, mew=2.2, zorder=5)
            ax.annotate(name, (c["failed_at"], yv), textcoords="offset points", xytext=(4, 6), fontsize=7,
                        color=cmap(colours[name]))
    if bound is not None:
        ax.axhline(bound, color="red", ls=":", lw=1, label=f"bound {bound:g}")
    if relative_bound is not None:
        ax.plot([], [], "x", color="red", label=f"failure: {metric} past {relative_bound:g}× unstressed, or NaN/Inf")
    elif bound is not None:
        ax.plot([], [], "x", color="red", label="failure point")
    xs_all = [x for c in curves.values() for x in c["x"] if math.isfinite(x)]
    pos = [x for x in xs_all if x > 0]
    if log_x is None:
        log_x = bool(pos) and max(pos) / min(pos) >= 20
    if log_x:
        if min(xs_all) > 0:
            ax.set_xscale("log")
        else:
            ax.set_xscale("symlog", linthresh=min(pos))
    lower = LOWER_IS_BETTER.get(metric, False) if better is None else better == "lower"
    if metric == "mse" and all(y > 0 for c in curves.values() for y in c["y"] if math.isfinite(y)):
        ax.set_yscale("log")
    ax.set_xlabel(axis + ("  (stress →)" if stress == "increasing" else "  (← stress)"))
    ax.set_ylabel(_LABELS.get(metric, metric) + (" ↓" if lower else " ↑"))
    ax.set_title(title or f"stability: {axis}", fontsize=9)
    ax.grid(True, alpha=0.3)
    outside_legend(ax)
    return fig, ax


def numerical_failures(rows) -> list[dict]:
    """Per method: runs, runs with NaN/Inf pixels, total NaN/Inf pixels, errored runs."""
    agg: "OrderedDict[str, dict]" = OrderedDict()
    for r in rows:
        a = agg.setdefault(r.get("method"), {"method": r.get("method"), "runs": 0, "runs_with_nonfinite": 0,
                                             "nonfinite_pixels": 0, "errors": 0})
        a["runs"] += 1
        if not _ok(r):
            a["errors"] += 1
            continue
        n = _f(r.get("n_nonfinite"))
        if math.isfinite(n) and n > 0:
            a["runs_with_nonfinite"] += 1
            a["nonfinite_pixels"] += int(n)
    return list(agg.values())

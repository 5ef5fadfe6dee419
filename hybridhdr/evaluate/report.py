"""Markdown + HTML benchmark report with image strips and charts (written by ``bench.write_results``)."""

from __future__ import annotations

import re
import math
import os
import time
from collections import OrderedDict
from pathlib import Path

import numpy as np

from .._util.atomic import atomic_path, write_text_atomic
from ..formats.images import tone_map
from .charts import _plt, numerical_failures, plot_speed_accuracy, plot_stability, stability_curves
from .metrics import JOD_NA

__all__ = ["summary_table", "akf_vs_cf", "akf_vs_cf_parts", "akf_vs_cf_text", "scoring_label", "jod_label",
           "write_report", "write_strip", "format_table", "render_report"]


def _f(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _num(v, fmt="{:.4g}") -> str:
    v = _f(v)
    return "n/a" if not math.isfinite(v) else fmt.format(v)


#: A run whose linear MSE exceeds this (the RMS error above the reference's maximum, on the
#: reference-max-normalised scale every metric uses) or whose metrics are not finite has blown up:
#: it is counted as a failure, never averaged into a headline (one diverged run at MSE 1e29 made a
#: pooled mean read "AKF MSE 997929738874 % higher").
BLOWUP_MSE = 1.0


def blown_up(r) -> bool:
    """An ``ok`` run whose reconstruction diverged: NaN/Inf pixels, or MSE not finite or above
    :data:`BLOWUP_MSE`."""
    if str(r.get("status", "")) != "ok":
        return False
    n = _f(r.get("n_nonfinite"))
    mse = _f(r.get("mse"))
    return (math.isfinite(n) and n > 0) or not math.isfinite(mse) or mse > BLOWUP_MSE


def summary_table(rows, datasets=None) -> list[dict]:
    """Median metrics and speed per (dataset, method_label) over ok runs that did not blow up
    (:func:`blown_up`; counted in ``blown_up``, never in a median)."""
    groups: "OrderedDict[tuple, list]" = OrderedDict()
    for r in rows:
        if datasets is not None and r.get("dataset") not in datasets:
            continue
        groups.setdefault((r.get("dataset"), r.get("method_label")), []).append(r)
    out = []
    for (ds, label), rs in groups.items():
        ran = [r for r in rs if r.get("status") == "ok"]
        ok = [r for r in ran if not blown_up(r)]

        def mean(k):  # the median: one outlier run cannot carry a row
            vals = [_f(r.get(k)) for r in ok]
            vals = [v for v in vals if not math.isnan(v)]
            return float(np.median(vals)) if vals else float("nan")
        norm = sorted({str(r.get("normalise")) for r in rs if r.get("normalise") not in (None, "", "none")})
        out.append({"dataset": ds, "method": label, "normalise": ",".join(norm) or "none", "runs": len(rs),
                    "ok": len(ok), "mse": mean("mse"),
                    "ssim": mean("ssim"), "log_mse": mean("log_mse"), "log_ssim": mean("log_ssim"),
                    "pu_ssim": mean("pu_ssim"), "pu_psnr_db": mean("pu_psnr_db"),
                    "q": mean("q"), "jod": mean("jod"), "time_per_data_s": mean("time_per_data_s"), "events_per_s": mean("events_per_s"),
                    "peak_rss_mb": mean("peak_rss_mb"),
                    "nonfinite": int(sum(v for v in (_f(r.get("n_nonfinite")) for r in ran) if math.isfinite(v))),
                    "blown_up": sum(blown_up(r) for r in ran)})
    return out


def akf_vs_cf(rows, datasets=None, akf_label: str = "akf", cf_label: str = "cf") -> dict | None:
    """AKF vs CF on matching datasets: MSE reduction and SSIM improvement in % (paper: 48 %, 11 %).

    Each method's value on a dataset is the median over its runs there that did not blow up
    (:func:`blown_up`); the figures are the geometric mean of those per-dataset medians (errors
    span orders of magnitude between datasets: an arithmetic mean is one dataset's), so the MSE
    reduction is ``1 - geomean(AKF / CF)``. Blown-up and errored runs are counted in
    ``akf_failed``/``cf_failed`` out of ``akf_runs``/``cf_runs``."""
    def by(label):
        d, runs, failed = {}, 0, 0
        for r in rows:
            if r.get("method_label") != label or (datasets is not None and r.get("dataset") not in datasets):
                continue
            runs += 1
            if r.get("status") != "ok" or blown_up(r):
                failed += 1
                continue
            d.setdefault(r["dataset"], []).append(r)
        return d, runs, failed
    (a, a_runs, a_failed), (c, c_runs, c_failed) = by(akf_label), by(cf_label)
    common = sorted(set(a) & set(c))
    if not common:
        return None

    def m(d, k):
        meds = []
        for key in common:
            vals = [v for v in (_f(r.get(k)) for r in d[key]) if math.isfinite(v)]
            meds.append(float(np.median(vals)) if vals else float("nan"))
        meds = np.asarray(meds)
        if not np.all(np.isfinite(meds)):
            return float("nan")
        if np.all(meds > 0):
            return float(np.exp(np.mean(np.log(meds))))
        return float(np.mean(meds))  # SSIM may be <= 0: the plain mean of the medians
    out = {"datasets": common, "akf_runs": a_runs, "akf_failed": a_failed, "cf_runs": c_runs, "cf_failed": c_failed}
    for k in ("mse", "ssim", "log_mse", "log_ssim", "pu_ssim"):
        out[f"akf_{k}"], out[f"cf_{k}"] = m(a, k), m(c, k)
    for k in ("mse", "log_mse"):
        cm = out[f"cf_{k}"]
        out[f"{k}_reduction_pct"] = 100.0 * (cm - out[f"akf_{k}"]) / cm if cm > 0 else float("nan")
    for k in ("ssim", "log_ssim", "pu_ssim"):
        cs = out[f"cf_{k}"]
        out[f"{k}_improvement_pct"] = 100.0 * (out[f"akf_{k}"] - cs) / cs if cs > 0 else float("nan")
    return out


def scoring_label(rows) -> str:
    """How the rows were scored: "unaltered reconstructions (normalise=none)" or the fits used."""
    modes = sorted({str(r.get("normalise")) for r in rows if r.get("normalise")})
    if not modes or modes == ["none"]:
        return ("unaltered reconstructions (normalise=none; references in frame-linear units, 1.0 = the frame "
                "camera's clip level)")
    if "none" in modes:
        fits = [m for m in modes if m != "none"]
        return f"unaltered reconstructions (normalise=none) except runs with a fitted normalisation ({', '.join(fits)})"
    return f"reconstructions fitted to the reference per run by least squares (normalise={', '.join(modes)})"


def jod_label(rows) -> str:
    """What the JOD column means: the display model and viewing distance of every score (one
    line per distinct display), the frames scored, or why there is no JOD."""
    lines = sorted({str(r.get("jod_display_line")) for r in rows if r.get("jod_display_line")})
    frames = [_f(r.get("jod_frames")) for r in rows if r.get("jod_display_line")]
    frames = [int(v) for v in frames if math.isfinite(v)]
    if lines:
        most = max(frames) if frames else 0
        return (f"Perceptual score: {'; '.join(lines)}; on at most {most} evenly spaced matched frames per run, each scored "
                f"as an image against its reference (mean), on the same [0, 1] pair as MSE/SSIM")
    if any(r.get("jod_note") == JOD_NA for r in rows):
        return f"JOD (ColorVideoVDP) {JOD_NA}"
    return "JOD (ColorVideoVDP) not computed (jod = false / --no-jod)"


def _lower(pct: float) -> str:
    """'12.3% lower' / '4.5% higher' for an MSE reduction in %."""
    if not math.isfinite(pct):
        return "n/a"
    return f"{pct:.1f}% lower" if pct >= 0 else f"{-pct:.1f}% higher"


def akf_vs_cf_parts(c: dict) -> list[dict]:
    """The AKF vs CF paragraph as text runs (``{"text", "style"}``, style "" or "b" for bold): the
    report templates render them as Markdown or HTML."""
    return [
        _run(f"On {', '.join(c['datasets'])} (per-dataset medians, geometric mean over datasets; failed or "
             f"blown-up runs: AKF {c.get('akf_failed', 0)}/{c.get('akf_runs', '?')}, CF {c.get('cf_failed', 0)}/"
             f"{c.get('cf_runs', '?')}, not averaged): linear MSE AKF {c['akf_mse']:.4g} vs CF {c['cf_mse']:.4g} ("),
        _run(f"AKF MSE {_lower(c['mse_reduction_pct'])}", "b"),
        _run(f"; paper: 48% lower), linear SSIM AKF {c['akf_ssim']:.3f} vs CF {c['cf_ssim']:.3f} ("),
        _run(f"{c['ssim_improvement_pct']:+.1f}% SSIM", "b"),
        _run(f"; paper: +11%). In log intensity: MSE {c['akf_log_mse']:.4g} vs {c['cf_log_mse']:.4g} "
             f"({_lower(c['log_mse_reduction_pct'])}), SSIM {c['akf_log_ssim']:.3f} vs {c['cf_log_ssim']:.3f} "
             f"({c['log_ssim_improvement_pct']:+.1f}%)."),
    ]


def akf_vs_cf_text(c: dict) -> str:
    """One Markdown paragraph: the AKF vs CF comparison, with the paper's figures beside ours."""
    return str(_macro("report.md.j2", "rich")(akf_vs_cf_parts(c)))


def format_table(header, body) -> str:
    """A Markdown table (rendered by the report template's table macro; '|' in a cell is escaped)."""
    return str(_macro("report.md.j2", "table")({"header": list(header), "rows": [list(r) for r in body]}))


# ----------------------------------------------------------------------------------------------
# templates (hybridhdr/evaluate/templates/*.j2; Jinja2, HTML autoescaped)


def _run(text, style: str = "") -> dict:
    """One run of a paragraph: plain, "b" (bold) or "code"."""
    return {"text": str(text), "style": style}


def _md_runs(text: str) -> list[dict]:
    """Runs of a paragraph written with Markdown's `code` and **bold** marks (the marks removed)."""
    runs, pos = [], 0
    for m in re.finditer(r"`([^`]+)`|\*\*([^*]+)\*\*", str(text)):
        if m.start() > pos:
            runs.append(_run(text[pos:m.start()]))
        runs.append(_run(m.group(1), "code") if m.group(1) is not None else _run(m.group(2), "b"))
        pos = m.end()
    if pos < len(str(text)):
        runs.append(_run(str(text)[pos:]))
    return runs


_ENV = None


def _env():
    """The Jinja2 environment of the report templates (autoescape on for ``*.html.j2``)."""
    global _ENV
    if _ENV is None:
        try:
            import jinja2
        except ImportError as e:  # pragma: no cover - jinja2 is in the images extra
            raise ImportError("the benchmark report needs jinja2: pip install 'hybridhdr[images]'") from e
        env = jinja2.Environment(
            loader=jinja2.PackageLoader("hybridhdr.evaluate", "templates"),
            autoescape=jinja2.select_autoescape(enabled_extensions=("html.j2", "html"), default_for_string=False,
                                                default=False),
            trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True,
            undefined=jinja2.StrictUndefined)
        # a '|' would end a Markdown table cell and a newline the row
        env.filters["md_cell"] = lambda v: str(v).replace("|", "\\|").replace("\r", " ").replace("\n", " ")
        _ENV = env
    return _ENV


def _macro(template: str, name: str):
    return getattr(_env().get_template(template).module, name)


def render_report(template: str, context: dict) -> str:
    """``report.md.j2`` or ``report.html.j2`` filled with ``context`` (see :func:`write_report`)."""
    return _env().get_template(template).render(**context)


def _md_inline_html(text: str) -> str:
    """One Markdown paragraph as HTML: escaped, with `code` and **bold** rendered (no literal marks)."""
    return str(_macro("report.html.j2", "rich")(_md_runs(text)))


def safe_file_stem(name: str) -> str:
    """``name`` usable as a file name on every OS: characters other than letters, digits, '.', '-'
    and '_' (e.g. the ':' of ``HDR:dark_room_window``) become '_'."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._") or "unnamed"


def write_strip(images: dict, path, title: str = "") -> Path:
    """One row of images: LDR input, each method, reference (tone-mapped with the reference's range)."""
    plt = _plt()
    ref = images.get("__reference__")
    ldr = images.get("__ldr__")
    methods = [k for k in images if not k.startswith("__")]
    panels = ([("LDR input", ldr, True)] if ldr is not None else []) + [(m, images[m], False) for m in methods] + \
             ([("reference", ref, False)] if ref is not None else [])
    _, lim = tone_map(ref[None]) if ref is not None else (None, None)
    ncol = min(len(panels), 7)
    nrow = -(-len(panels) // ncol)
    hw = (np.asarray(panels[0][1]).shape[0] / max(np.asarray(panels[0][1]).shape[1], 1)) if panels else 0.75
    fig, axes = plt.subplots(nrow, ncol, figsize=(2.1 * ncol, nrow * (2.1 * hw + 0.35) + 0.3), squeeze=False)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    for ax, (name, img, raw) in zip(axes.ravel(), panels):
        if raw:
            ax.imshow(np.asarray(img), cmap="gray", vmin=0, vmax=255 if np.asarray(img).dtype.kind in "ui" else 1)
        else:
            tm, _ = tone_map(np.asarray(img, np.float64)[None], limits=lim)
            ax.imshow(tm[0], cmap="gray", vmin=0, vmax=255)
        ax.set_title(name if len(name) < 28 else name[:26] + "…", fontsize=7)
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    path = Path(path)
    try:
        with atomic_path(path, ".png") as tmp:
            fig.savefig(tmp, dpi=110)
    finally:
        plt.close(fig)
    return path


def _save(fig, path: Path):
    try:
        with atomic_path(path, ".png") as tmp:
            fig.savefig(tmp, dpi=120, bbox_inches="tight")
    finally:
        _plt().close(fig)
    return path


def write_charts(rows, out: Path, charts_cfg: dict) -> tuple[dict, list]:
    """Speed–accuracy and stability PNGs; returns (paths, stability failure rows)."""
    plt = __import__("hybridhdr.evaluate.charts", fromlist=["_plt"])._plt()
    paths, fails = {}, []
    sa = charts_cfg.get("speed_accuracy", {})
    if sa is not False:
        sa = sa if isinstance(sa, dict) else {}
        metrics = [m for m in sa.get("metrics", ["mse", "ssim", "jod", "q"])]
        # a panel with no data is not drawn (e.g. HDR-VDP Q without an HDR-VDP installation)
        metrics = [m for m in metrics if any(math.isfinite(_f(r.get(m))) for r in rows)] or metrics[:1]
        fig, axes = plt.subplots(1, len(metrics), figsize=(5.6 * len(metrics), 4.4), squeeze=False)
        for ax, m in zip(axes[0], metrics):
            plot_speed_accuracy(rows, m, sa.get("datasets"), ax=ax)
        paths["speed_accuracy"] = _save(fig, out / "speed_accuracy.png")
    sm = charts_cfg.get("sampling")
    if sm:
        metrics = list(sm.get("metrics", ["mse", "ssim", "log_ssim"]))
        fig, axes = plt.subplots(1, len(metrics), figsize=(5.6 * len(metrics), 4.4), squeeze=False)
        for ax, m in zip(axes[0], metrics):
            plot_speed_accuracy([r for r in rows if r.get("method_name", r.get("method")) == sm.get("method", "akf")],
                                m, sm.get("datasets"), ax=ax, group_by="dataset_variant",
                                time_column="dataset_time_per_data_s",
                                xlabel="simulation wall time per second of data (s/s)",
                                title=f"simulator sampling vs {sm.get('method', 'akf')} {m}")
        paths["sampling"] = _save(fig, out / "sampling_speed_accuracy.png")
    st = charts_cfg.get("stability", [])
    if isinstance(st, dict):
        st = [st]
    if st:
        n = len(st)
        ncol = min(3, n)
        nrow = math.ceil(n / ncol)
        fig, axes = plt.subplots(nrow, ncol, figsize=(5.4 * ncol, 4.0 * nrow), squeeze=False)
        for ax in axes.ravel()[n:]:
            ax.axis("off")
        for ax, s in zip(axes.ravel(), st):
            kw = {k: s[k] for k in ("dataset", "axis", "metric", "bound", "better", "stress", "relative_bound")
                  if k in s}
            plot_stability(rows, title=s.get("title"), ax=ax, log_x=s.get("log_x"), **kw)
            for name, c in stability_curves(rows, **kw).items():
                fails.append({"stress": s.get("title") or s["axis"], "axis": s["axis"], "method": name,
                              "failed_at": c["failed_at"], "reason": c["reason"] or "none within the sweep",
                              "nonfinite": int(sum(c["nonfinite"]))})
        fig.tight_layout()
        paths["stability"] = _save(fig, out / "stability.png")
    return paths, fails


def write_report(rows, out, bench=None, *, charts: bool = True) -> dict:
    """Write strips, charts, ``report.md`` and ``report.html``; returns name -> Path."""
    out = Path(out)
    written = {}
    # strips: first and last variant of each dataset, capped by bench.strips
    cap = getattr(bench, "strips", 4) if bench is not None else 4
    by_ds: "OrderedDict[str, list]" = OrderedDict()
    for r in rows:
        if "_strip" in r and r["_strip"]:
            by_ds.setdefault(r["dataset"], []).append(r)
    strip_paths = []
    (out / "strips").mkdir(exist_ok=True)
    for ds, rs in by_ds.items():
        pick = [rs[0]] + ([rs[-1]] if len(rs) > 1 else [])
        for r in pick:
            if len(strip_paths) >= cap:
                break
            gv = ", ".join(f"{k[3:]}={r[k]}" for k in r if k.startswith("ds."))
            p = write_strip(r["_strip"], out / "strips" / f"strip_{r['task']:03d}_{safe_file_stem(ds)}.png",
                            title=f"{ds}" + (f" ({gv})" if gv else ""))
            strip_paths.append(p)
    chart_paths, fails = ({}, [])
    if charts and rows:
        chart_paths, fails = write_charts(rows, out, getattr(bench, "charts", {}) or {})
    written.update(chart_paths)
    summ = summary_table(rows)
    header = ["dataset", "method", "MSE", "SSIM", "log MSE", "log SSIM", "PU-SSIM", "JOD", "Q", "time/s data", "Mev/s",
              "peak RSS MB", "NaN/Inf px", "blown up", "ok/runs"]
    body = [[s["dataset"], s["method"] + ("" if s["normalise"] == "none" else f" (fitted: {s['normalise']})"),
             _num(s["mse"]), _num(s["ssim"], "{:.3f}"), _num(s["log_mse"]),
             _num(s["log_ssim"], "{:.3f}"), _num(s["pu_ssim"], "{:.3f}"), _num(s["jod"], "{:.2f}"),
             _num(s["q"], "{:.2f}"), _num(s["time_per_data_s"], "{:.3g}"),
             _num(s["events_per_s"] / 1e6 if math.isfinite(s["events_per_s"]) else float("nan"), "{:.3g}"),
             _num(s["peak_rss_mb"], "{:.0f}"), s["nonfinite"], s["blown_up"], f"{s['ok']}/{s['runs']}"] for s in summ]
    nf = numerical_failures(rows)
    nf_body = [[n["method"], n["runs"], n["runs_with_nonfinite"], n["nonfinite_pixels"], n["errors"]] for n in nf]
    cmp_ = akf_vs_cf(rows)
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    name = getattr(bench, "name", "bench")
    errs = [r for r in rows if r.get("status") != "ok"]
    chart_titles = (("speed_accuracy", "Speed–accuracy"), ("sampling", "Simulator sampling: speed–accuracy"),
                    ("stability", "Stability"))
    context = {
        "name": name,
        "intro": [_run(f"Generated {time.strftime('%Y-%m-%d %H:%M:%S')}; load average {load[0]:.2f} {load[1]:.2f} "
                       f"{load[2]:.2f} (timings are noisy on a shared machine). {len(rows)} runs.")],
        "scoring": _md_runs(
            f"Scoring (see docs/evaluate.md): {scoring_label(rows)}; both divided by the reference "
            "maximum, reconstruction not clipped (symmetric); MSE and SSIM (Gaussian σ = 1.5, data range 1) on that; "
            f"PU21 on ×{getattr(bench, 'peak_luminance_cd_m2', 4000.0):g} cd/m²; frames matched to references within "
            f"{getattr(bench, 'tolerance_us', 1000)} µs. {jod_label(rows)}. Q (HDR-VDP 3, for comparison with the "
            "paper's Q) is n/a without an HDR-VDP 3 installation."),
        "results": {"header": header, "rows": body},
        "akf_vs_cf": akf_vs_cf_parts(cmp_) if cmp_ is not None else None,
        "numerical_failures": {"header": ["method", "runs", "runs with NaN/Inf", "NaN/Inf pixels", "errored runs"],
                               "rows": nf_body},
        # prose may carry `code` marks (error hints): runs, rendered as code spans in HTML
        "errors": [_md_runs(f"{r['dataset']} / {r['method_label']}: {r.get('status')}") for r in errs[:20]],
        "stability": ({"header": ["stress", "method", "failed at", "reason", "NaN/Inf pixels"],
                       "rows": [[f["stress"], f["method"], "—" if f["failed_at"] is None else f"{f['failed_at']:g}",
                                 _md_runs(f["reason"]), f["nonfinite"]] for f in fails]} if fails else None),
        "charts": [{"title": title, "src": chart_paths[k].name} for k, title in chart_titles if k in chart_paths],
        "strips": [{"alt": p.stem, "src": f"strips/{p.name}"} for p in strip_paths],
    }
    for template, fname, key in (("report.md.j2", "report.md", "report_md"),
                                 ("report.html.j2", "report.html", "report_html")):
        text = render_report(template, context).rstrip("\n") + "\n"
        written[key] = write_text_atomic(out / fname, text)
    written["strips"] = strip_paths
    written["failures"] = fails
    written["akf_vs_cf"] = cmp_
    return written

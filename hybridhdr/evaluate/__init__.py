"""Evaluate: score reconstructions — metrics (MSE, PSNR, SSIM, PU21, HDR-VDP, ColorVideoVDP), TOML
benchmarks and their datasets, reports, speed–accuracy and stability charts, Table 1 of the paper.

See ``docs/evaluate.md``.
"""

from .._util.lazy import lazy_exports

# Lazy (PEP 562): the names below load their module on first use, so that building the command
# line's parser (hybridhdr --help) does not import numba and the kernels (a slow start).
_LAZY = {
    'bundled_bench': '.bench',
    'load_bench': '.bench',
    'run_bench': '.bench',
    'plot_speed_accuracy': '.charts',
    'plot_stability': '.charts',
    'Dataset': '.datasets',
    'load_dataset': '.datasets',
    'global_ssim': '.metrics',
    'hdrvdp_q': '.metrics',
    'mse': '.metrics',
    'psnr': '.metrics',
    'pu_psnr': '.metrics',
    'pu_ssim': '.metrics',
    'score_video': '.metrics',
    'ssim': '.metrics',
    'paper_table': '.paper',
    'run_paper': '.paper',
    'evaluate_holdout': '.realdata',
    'write_report': '.report',
    'stability_bench': '.sweeps',
}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)


__all__ = [
    "mse", "psnr", "ssim", "global_ssim", "pu_psnr", "pu_ssim", "score_video", "hdrvdp_q",
    "load_bench", "bundled_bench", "run_bench", "Dataset", "load_dataset", "write_report",
    "plot_speed_accuracy", "plot_stability", "stability_bench", "paper_table", "run_paper", "evaluate_holdout",
]

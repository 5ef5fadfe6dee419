"""Evaluate: score reconstructions — metrics (MSE, PSNR, SSIM, PU21, HDR-VDP, ColorVideoVDP), TOML
benchmarks and their datasets, reports, speed–accuracy and stability charts, Table 1 of the paper.

See ``docs/evaluate.md``.
"""

from .bench import bundled_bench, load_bench, run_bench
from .charts import plot_speed_accuracy, plot_stability
from .datasets import Dataset, load_dataset
from .metrics import global_ssim, hdrvdp_q, mse, psnr, pu_psnr, pu_ssim, score_video, ssim
from .paper import paper_table, run_paper
from .realdata import evaluate_holdout
from .report import write_report
from .sweeps import stability_bench

__all__ = [
    "mse", "psnr", "ssim", "global_ssim", "pu_psnr", "pu_ssim", "score_video", "hdrvdp_q",
    "load_bench", "bundled_bench", "run_bench", "Dataset", "load_dataset", "write_report",
    "plot_speed_accuracy", "plot_stability", "stability_bench", "paper_table", "run_paper", "evaluate_holdout",
]

"""Figures of the studies over many runs: the SO(3) launch CDFs and the sweep summary."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

LABELS = {"geometric": "geometric SE(3) (large-angle)", "pid": "PID cascade"}


def _cdf(ax, values: np.ndarray, label: str) -> None:
    """Empirical CDF; NaN (never settled) stays off the curve, so it ends below 1."""
    n = len(values)
    x = np.sort(values[np.isfinite(values)])
    ax.step(x, np.arange(1, len(x) + 1) / max(n, 1), where="post", label=label)


def fig_launch_cdf(study, out: Path) -> Path:
    """CDFs of settle time, height lost and drift over the SO(3) draws, geometric vs PID.

    study: a launch_so3.So3Study.
    """
    fig, axs = plt.subplots(1, 3, figsize=(14, 4.2))
    panels = (("settle_time_s", "settle time (s)"), ("altitude_loss_m", "height lost (m)"), ("drift_m", "drift (m)"))
    for ax, (name, xlabel) in zip(axs, panels):
        for b in (study.geometric, study.pid):
            _cdf(ax, np.asarray(getattr(b, name), float), LABELS[b.controller])
        ax.set_xlabel(xlabel)
        ax.set_ylabel("fraction of releases")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    axs[0].legend(loc="lower right", fontsize=8)
    fig.suptitle(f"{study.draws.n} releases at uniformly random attitudes, body rates up to "
                 f"{study.body_rate_max_radps:g} rad/s, {study.speed_mps:g} m/s from {study.release_height_m:g} m")
    fig.tight_layout()
    p = out / "fig_launch_so3_cdf.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def fig_sweep(runs, safety_distance_m: float, out: Path) -> Path:
    """Sweep summary: CDFs of minimum separation, worst settle time and completion time.

    runs: list of sweep.SweepRun (crashed runs are counted in the denominators).
    """
    fig, axs = plt.subplots(1, 3, figsize=(14, 4.2))
    panels = (("min_separation_m", "minimum pair separation (m)"), ("max_settle_time_s", "worst recovery time in run (s)"),
              ("completion_time_s", "mission completion time (s)"))
    for ax, (name, xlabel) in zip(axs, panels):
        vals = np.array([np.nan if getattr(r, name) is None else getattr(r, name) for r in runs], float)
        _cdf(ax, vals, f"{np.isfinite(vals).sum()} of {len(runs)} runs")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("fraction of runs")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)
    axs[0].axvline(safety_distance_m, color="red", linestyle="--", linewidth=1)
    passed = sum(r.ok and r.passed for r in runs)
    met = sum(r.target_met for r in runs)
    fig.suptitle(f"{len(runs)} seeds: {met} finished with every healthy vehicle and no collision, "
                 f"{passed} passed every check")
    fig.tight_layout()
    p = out / "fig_sweep.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p

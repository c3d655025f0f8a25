"""PNG figures matching the paper's (Fig. 2/3, 5, 6, 7, 8, 9, 10).

Plots show "up" (= -z NED) on the vertical axis, as the paper does.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from companion import frames  # noqa: E402
from companion.agent import Phase  # noqa: E402
from sim_bridge.reports.metrics import formation_deviation  # noqa: E402
from sim_bridge.reports.record import RunResult  # noqa: E402


def _sphere(ax, centre_ned, radius, color="hotpink", alpha=0.35):
    u, v = np.mgrid[0 : 2 * np.pi : 30j, 0 : np.pi : 15j]
    n = centre_ned[0] + radius * np.cos(u) * np.sin(v)
    e = centre_ned[1] + radius * np.sin(u) * np.sin(v)
    up = -centre_ned[2] + radius * np.cos(v)
    ax.plot_surface(e, n, up, color=color, alpha=alpha, linewidth=0)


def _obstacles(ax, result: RunResult):
    for c, r in zip(result.mission.obstacle_centres_ned_m, result.mission.obstacle_radii_m):
        _sphere(ax, c, r)


def _axes3d(fig, pos=(1, 1, 1), title=""):
    ax = fig.add_subplot(*pos, projection="3d")
    ax.set_xlabel("East (m)")
    ax.set_ylabel("North (m)")
    ax.set_zlabel("Up (m)")
    ax.set_title(title)
    return ax


def fig_launch(traces: dict, out: Path) -> list[Path]:
    """Fig. 2 vs 3: attitude, speed and position after a launch, geometric vs PID."""
    paths = []
    for roll, pair in traces.items():
        fig, axs = plt.subplots(3, 2, figsize=(11, 9), sharex=True)
        for col, name in enumerate(("geometric", "pid")):
            tr = pair[name]
            eul = np.degrees(tr.euler_rad)
            for k, lab in enumerate(("roll", "pitch", "yaw")):
                axs[0, col].plot(tr.t_s, eul[:, k], label=lab)
            for k, lab in enumerate(("v_N", "v_E", "v_D")):
                axs[1, col].plot(tr.t_s, tr.vel_ned_mps[:, k], label=lab)
                axs[2, col].plot(tr.t_s, tr.pos_ned_m[:, k] - tr.pos_ned_m[0, k], label=lab.replace("v_", ""))
            axs[0, col].set_title(f"{'Geometric SE(3)' if name == 'geometric' else 'PID cascade'}: roll {roll:g} deg at launch")
            axs[0, col].set_ylabel("attitude (deg)")
            axs[1, col].set_ylabel("velocity (m/s)")
            axs[2, col].set_ylabel("displacement (m)")
            axs[2, col].set_xlabel("time since release (s)")
            for r in range(3):
                axs[r, col].grid(alpha=0.3)
                axs[r, col].legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        p = out / f"fig2_3_launch_recovery_roll{roll:g}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def fig_trajectories(result: RunResult, out: Path) -> Path:
    """Fig. 5: every trajectory, launch points, final positions and the obstacle."""
    pos = result.log["pos_ned_m"]
    fig = plt.figure(figsize=(10, 8))
    ax = _axes3d(fig, title=f"{result.mission.n} vehicles: whole mission")
    for v in range(pos.shape[1]):
        flying = result.log["t_s"] >= result.release_s[v]
        ax.plot(pos[flying, v, 1], pos[flying, v, 0], -pos[flying, v, 2], lw=0.6)
    rp = result.release_pos_ned_m
    ax.scatter(rp[:, 1], rp[:, 0], -rp[:, 2], facecolors="none", edgecolors="red", s=25, label="launch points")
    ax.scatter(pos[-1, :, 1], pos[-1, :, 0], -pos[-1, :, 2], marker="*", color="blue", s=30, label="final positions")
    _obstacles(ax, result)
    ax.legend(loc="upper left")
    p = out / "fig5_trajectories_3d.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def fig_attitude_recovery(result: RunResult, vehicles: Sequence[int], out: Path, window_s: float = 4.0) -> Path:
    """Fig. 6: roll/pitch/yaw after release for the chosen (1-based) vehicles."""
    t = result.log["t_s"]
    eul = np.degrees(frames.rot_to_euler_zyx(frames.quat_wxyz_to_rot(result.log["att_q_wxyz"].astype(float))))
    vehicles = [v for v in vehicles if 1 <= v <= result.mission.n]
    fig, axs = plt.subplots(len(vehicles), 1, figsize=(8, 2.4 * len(vehicles)), sharex=True, squeeze=False)
    for ax, v in zip(axs[:, 0], vehicles):
        sel = (t >= result.release_s[v - 1]) & (t <= result.release_s[v - 1] + window_s)
        for k, lab in enumerate(("roll", "pitch", "yaw")):
            ax.plot(t[sel] - result.release_s[v - 1], eul[sel, v - 1, k], label=lab)
        ax.set_ylabel(f"UAV {v} (deg)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axs[-1, 0].set_xlabel("time since release (s)")
    fig.suptitle("Attitude recovery after launch")
    fig.tight_layout()
    p = out / "fig6_attitude_recovery.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def fig_assembly(result: RunResult, out: Path) -> Path:
    """Fig. 7: top view of the assembly stage, from release to transit start."""
    t, pos = result.log["t_s"], result.log["pos_ned_m"]
    t_end = result.t_go_s if not math.isnan(result.t_go_s) else t[-1]
    fig, ax = plt.subplots(figsize=(8, 8))
    for v in range(pos.shape[1]):
        sel = (t >= result.release_s[v]) & (t <= t_end)
        ax.plot(pos[sel, v, 1], pos[sel, v, 0], lw=0.7)
    slots = result.mission.offsets_ned_m + result.mission.path.at(-1.0)[0]
    ax.scatter(slots[:, 1], slots[:, 0], marker="o", facecolors="none", edgecolors="k", s=40, label="formation slots")
    rp = result.release_pos_ned_m
    ax.scatter(rp[:, 1], rp[:, 0], color="red", s=10, label="launch points")
    ax.set_xlabel("East (m)")
    ax.set_ylabel("North (m)")
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(f"Formation assembly (until t = {t_end:.0f} s)")
    p = out / "fig7_formation_assembly.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def fig_deviation(result: RunResult, out: Path) -> Path:
    """Fig. 8: maximum formation deviation over time."""
    t, dev = formation_deviation(result)
    fig, ax = plt.subplots(figsize=(9, 4.5))
    ax.semilogy(t, np.maximum(dev, 1e-4))
    if not math.isnan(result.t_go_s):
        ax.axvline(result.t_go_s, color="g", ls="--", label="transit start")
        ax.axvline(result.t_go_s + result.mission.path.duration_s, color="m", ls="--", label="hover")
    ax.axhline(result.cfg.completion_tol_m, color="r", ls=":", label=f"{result.cfg.completion_tol_m} m")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("max |p_i - h_i| (m)")
    ax.set_title("Maximum formation deviation")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    p = out / "fig8_formation_deviation.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def fig_avoidance(result: RunResult, first_last: tuple[int, int], out: Path) -> Path:
    """Fig. 9: transit trajectories of a group of vehicles past the obstacle."""
    t, pos = result.log["t_s"], result.log["pos_ned_m"]
    sel = t >= (result.t_go_s if not math.isnan(result.t_go_s) else t[-1])
    lo, hi = max(1, first_last[0]), min(result.mission.n, first_last[1])
    fig = plt.figure(figsize=(14, 6.5))
    ax = _axes3d(fig, (1, 2, 1), title=f"UAVs {lo}-{hi} during transit")
    ax2 = fig.add_subplot(122)
    for v in range(lo - 1, hi):
        ax.plot(pos[sel, v, 1], pos[sel, v, 0], -pos[sel, v, 2], lw=0.9, label=f"UAV {v + 1}")
        ax2.plot(pos[sel, v, 1], pos[sel, v, 0], lw=0.9)
    _obstacles(ax, result)
    for c, r in zip(result.mission.obstacle_centres_ned_m, result.mission.obstacle_radii_m):
        ax2.add_patch(plt.Circle((c[1], c[0]), r, color="hotpink", alpha=0.4))
    ax2.set_aspect("equal")
    ax2.set_xlabel("East (m)")
    ax2.set_ylabel("North (m)")
    ax2.set_title("top view")
    ax2.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    p = out / "fig9_avoidance.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def fig_snapshots(result: RunResult, times_s: tuple[float, ...], out: Path) -> Path:
    """Fig. 10: where every airborne vehicle is at the chosen times."""
    t, pos, phase = result.log["t_s"], result.log["pos_ned_m"], result.log["phase"]
    times = [x for x in times_s if x <= t[-1]] or [t[-1]]
    cols = min(4, len(times))
    rows = math.ceil(len(times) / cols)
    fig = plt.figure(figsize=(4.2 * cols, 4.0 * rows))
    for k, ts in enumerate(times):
        i = int(np.argmin(np.abs(t - ts)))
        ax = _axes3d(fig, (rows, cols, k + 1), title=f"t = {t[i]:.0f} s")
        fly = phase[i] >= Phase.STABILISE
        ax.scatter(pos[i, fly, 1], pos[i, fly, 0], -pos[i, fly, 2], s=6, color="tab:blue")
        _obstacles(ax, result)
    fig.tight_layout()
    p = out / "fig10_snapshots.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    return p


def write_figures(result: RunResult, traces: dict | None, out: Path) -> list[Path]:
    o = result.cfg.output
    paths = [] if traces is None else fig_launch(traces, out)
    paths += [
        fig_trajectories(result, out),
        fig_attitude_recovery(result, o.attitude_vehicles, out),
        fig_assembly(result, out),
        fig_deviation(result, out),
        fig_avoidance(result, o.avoidance_vehicles, out),
        fig_snapshots(result, o.snapshot_times_s, out),
    ]
    return paths

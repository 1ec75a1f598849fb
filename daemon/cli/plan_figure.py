"""Top view of a plan (matplotlib, PNG): part contour, AGV stations, tracker stations, covers, transfer order,
and the areas the plan leaves out (by reason, marker size by area, labelled with area and height range)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - the backend is chosen first
import numpy as np  # noqa: E402
from tandemscan.pipeline.planning.coverage import (  # noqa: E402
    REASON_MISSED,
    REASON_NO_POSE,
    REASON_REACH,
    REASON_TRACKER,
)
from tandemscan.pipeline.planning.planner import PartPlan, target_poses  # noqa: E402


def draw_plan(plan: PartPlan, T_T_S: np.ndarray, path: Path, title: str = "") -> None:
    """Write the top view of ``plan`` to ``path`` (PNG). Floor frame F, metres on the axes."""
    fig, ax = plt.subplots(figsize=(11, 8), dpi=110)
    mm = 1e-3
    cx, cy = plan.layout.contour.exterior.xy
    ax.fill(np.array(cx) * mm, np.array(cy) * mm, color="0.85", label="part (floor contour)")
    px, py = plan.layout.path.exterior.xy
    ax.plot(np.array(px) * mm, np.array(py) * mm, color="0.6", lw=0.8, ls="--", label="AGV path")

    colours = plt.get_cmap("tab10")
    targets, _ = target_poses(plan.poses, T_T_S)
    order = np.array(plan.sequence.scan_order, int)
    owner = np.array(plan.sequence.scan_tracker_station, int)
    for k in range(plan.tracker.count):
        sel = order[owner == k]
        if len(sel):
            ax.scatter(targets[sel, 0] * mm, targets[sel, 1] * mm, s=4, color=colours(k % 10), alpha=0.6)

    for st in plan.layout.stations:
        ax.arrow(st.x_mm * mm, st.y_mm * mm, 0.25 * np.cos(st.heading_rad), 0.25 * np.sin(st.heading_rad),
                 head_width=0.08, color="k", lw=0.8)
        ax.annotate(str(st.index), (st.x_mm * mm, st.y_mm * mm), fontsize=7, xytext=(3, 3),
                    textcoords="offset points")
    ax.scatter(plan.candidates[:, 0] * mm, plan.candidates[:, 1] * mm, s=3, color="0.7", label="tracker candidates")

    chain = np.array(plan.tracker_chain)
    ax.plot(chain[:, 0] * mm, chain[:, 1] * mm, color="tab:red", lw=1.0, ls=":", label="tracker transfer order")
    for k, (x, y, h) in enumerate(chain):
        c = colours(k % 10)
        ax.scatter([x * mm], [y * mm], s=90, color=c, edgecolor="k", zorder=5)
        ax.arrow(x * mm, y * mm, 0.6 * np.cos(h), 0.6 * np.sin(h), head_width=0.12, color=c, zorder=5)
        ax.annotate(f"T{k + 1}", (x * mm, y * mm), fontsize=9, weight="bold", xytext=(6, -12),
                    textcoords="offset points")
    for t in plan.sequence.transfer_poses:
        ax.scatter([targets[t, 0] * mm], [targets[t, 1] * mm], marker="*", s=120, color="tab:red", edgecolor="k",
                   zorder=6)
    _draw_left_out(ax, plan)
    s = plan.summary()
    ax.set_title(title or (f"{s['scans']} scans at {s['agv_stations']} AGV stations, {s['tracker_stations']} tracker "
                           f"stations ({s['tracker_solver']}, bound {s['tracker_lower_bound']}), "
                           f"{s['transfers']} transfers (stars)"), fontsize=10)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, floor frame F)")
    ax.set_ylabel("y (m)")
    ax.grid(True, lw=0.3)
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


_LEFT_OUT_STYLE = {  # reason -> (colour, marker)
    REASON_REACH: ("tab:red", "X"),
    REASON_TRACKER: ("tab:purple", "D"),
    REASON_MISSED: ("tab:orange", "s"),
    REASON_NO_POSE: ("0.4", "v"),
}


def _draw_left_out(ax, plan: PartPlan) -> None:
    """The left-out areas at their centroids (F, m): one marker per reason and station, area 0.01 m^2 or more;
    those of 0.25 m^2 or more a scanner could see are labelled with their area and height range."""
    mm = 1e-3
    for reason, (colour, marker) in _LEFT_OUT_STYLE.items():
        areas = [lo for lo in plan.coverage.left_out if lo.reason == reason and lo.area_mm2 >= 1e4]
        if not areas:
            continue
        xy = np.array([lo.centroid_mm[:2] for lo in areas]) * mm
        size = 20 + 200 * np.sqrt(np.array([lo.area_mm2 for lo in areas]) / 1e6)
        total = sum(lo.area_mm2 for lo in areas) / 1e6
        ax.scatter(xy[:, 0], xy[:, 1], s=size, marker=marker, color=colour, alpha=0.6, edgecolor="k", zorder=7,
                   label=f"left out: {reason} ({total:.2f} m^2)")
        for lo in areas:
            if lo.area_mm2 >= 2.5e5 and reason != REASON_NO_POSE:
                z0, z1 = (z / 1e3 for z in lo.z_range_mm)
                ax.annotate(f"{lo.area_mm2 / 1e6:.2f} m^2, z {z0:.1f}-{z1:.1f} m",
                            (lo.centroid_mm[0] * mm, lo.centroid_mm[1] * mm), fontsize=6, color=colour,
                            xytext=(4, -8), textcoords="offset points")

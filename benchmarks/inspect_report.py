"""Inspection figures on the default part (parametric train nose, frame F, mm): signed-distance accuracy on
points with known offsets, throughput, and the time to build the full report. Prints one JSON object last.

Usage: nice python benchmarks/inspect_report.py [--points 1000000]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.config.models import InspectionConfig, PartConfig
from tandemscan.pipeline.geometry.part import train_nose_mesh
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionCriteria, inspect_cloud
from tandemscan.pipeline.inspection.report import InspectedPart, ReportStyle, build_report, write_report


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=1_000_000)
    args = ap.parse_args()
    mesh = train_nose_mesh(PartConfig())
    mesh.compute_triangle_normals()
    rng = np.random.default_rng(0)
    # known offsets: points on triangle interiors moved along that triangle's normal by up to 0.3 mm
    V, T = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    N = np.asarray(mesh.triangle_normals)
    tri = rng.integers(0, len(T), args.points)
    r = rng.uniform(0.2, 0.4, (args.points, 2))  # well inside the triangle: the projection stays on it
    a, b, c = V[T[tri, 0]], V[T[tri, 1]], V[T[tri, 2]]
    offsets = rng.uniform(-0.3, 0.3, args.points)
    pts = a + r[:, :1] * (b - a) + r[:, 1:] * (c - a) + offsets[:, None] * N[tri]
    surface = CadSurface(mesh)
    t0 = time.perf_counter()
    d = surface.signed_distance(pts)
    t_sd = time.perf_counter() - t0
    err_um = np.abs(d - offsets) * 1000.0
    cfg = InspectionConfig()
    t0 = time.perf_counter()
    result = inspect_cloud(pts, surface, InspectionCriteria.from_section(cfg))
    t_inspect = time.perf_counter() - t0
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as out:
        write_report(build_report(result, InspectedPart(surface), ReportStyle.from_section(cfg)), out)
    t_report = time.perf_counter() - t0
    publish("inspect_report", {
        "benchmark": "inspect_report",
        "points": args.points,
        "triangles": len(T),
        "known_offset_err_um_median": round(float(np.median(err_um)), 4),
        "known_offset_err_um_max": round(float(err_um.max()), 4),
        "signed_distance_s": round(t_sd, 3),
        "signed_distance_points_per_s": round(args.points / t_sd),
        "inspect_with_best_fit_s": round(t_inspect, 3),
        "report_build_s": round(t_report, 3),
        "best_fit_translation_um": round(result.best_fit.translation_mm * 1000.0, 3),
    })


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()

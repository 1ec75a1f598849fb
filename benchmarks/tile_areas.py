"""CPU seconds and traced memory of the tiled deviation areas' units against the tiles' inspection units
(docs/compute.md "Tiles", "Deviation areas from every point"), and whether the report's sample alone would see a
small dent that the tiles find.

Usage: nice -n 10 python benchmarks/tile_areas.py [--tiles 3] [--tile-mm 500] [--width-mm 1500] [--report-points N]

A generated flat part (1 mm jittered grid, 0.02 mm noise; the CAD two triangles) cut into ``--tiles`` slabs of
``--tile-mm`` across x, ``--width-mm`` wide, with a dent 0.5 mm deep (sigma 3 mm) in the second tile. Each tile's
units run one after the other in this process (``inspect_tile``, then ``find_tile_areas``): per unit its CPU
seconds and its traced peak (``tracemalloc``: NumPy's arrays; SciPy's KD tree nodes are not traced), per point.
``sample_finds_dent``: the areas of every k-th point up to ``--report-points`` (the report's sample) hold the dent
(20,000 on the default 2.25 m^2: 10 mm apart, as 1 M points on about 110 m^2).
Timings on a shared machine are unreliable: run it idle.
"""

from __future__ import annotations

import argparse
import contextlib
import shutil
import tempfile
import time
import tracemalloc
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from results import publish
from tandemscan.pipeline.compute import LocalBackend
from tandemscan.pipeline.inspection import tile_inspection
from tandemscan.pipeline.inspection.deviation_areas import DeviationCloud, find_deviation_areas
from tandemscan.pipeline.inspection.inspect import CadSurface
from tandemscan.pipeline.inspection.tile_inspection import AreaBounds, inspect_tiles, tile_areas, write_cad
from tandemscan.pipeline.stitching.tiles import TILES_FOLDER, TileCloud, TiledCloud

DENT = (0.5, 3.0)  # depth and sigma, mm
BOUNDS = AreaBounds(-0.1, 0.1, 4.0, 50.0)  # [inspection]'s defaults


def generated_part(store: Path, tiles: int, tile_mm: float, width_mm: float, dent_mm: tuple[float, float]
                   ) -> TiledCloud:
    """The flat part's tiles (W = F) in ``store``, the dent at ``dent_mm`` (x, y)."""
    rng = np.random.default_rng(0)
    (store / TILES_FOLDER).mkdir(parents=True, exist_ok=True)
    out = []
    for k in range(tiles):
        x, y = np.meshgrid(np.arange(k * tile_mm, (k + 1) * tile_mm), np.arange(0.0, width_mm), indexing="ij")
        p = np.c_[x.ravel() + rng.uniform(-0.3, 0.3, x.size), y.ravel() + rng.uniform(-0.3, 0.3, x.size),
                  rng.normal(0.0, 0.02, x.size)]
        p[:, 2] -= DENT[0] * np.exp(-((p[:, 0] - dent_mm[0]) ** 2 + (p[:, 1] - dent_mm[1]) ** 2) / (2 * DENT[1] ** 2))
        file = f"{TILES_FOLDER}/part-{k:03d}.npz"
        np.savez(store / file, points=p, normals=np.tile([0.0, 0.0, 1.0], (len(p), 1)),
                 counts=np.ones(len(p), np.int64))
        out.append(TileCloud(k, file, len(p)))
    return TiledCloud(1.0, str(store), tuple(out))


def flat_cad(path: Path, length_mm: float, width_mm: float) -> Path:
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector([[-10, -10, 0], [length_mm + 10, -10, 0], [-10, width_mm + 10, 0],
                                    [length_mm + 10, width_mm + 10, 0]]),
        o3d.utility.Vector3iVector([[0, 1, 2], [1, 3, 2]]))
    o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def measured(fn, log: list[tuple[float, int]]):
    """``fn`` wrapped so that each call's CPU seconds and traced peak (bytes) go into ``log``."""
    def run(unit):
        tracemalloc.start()
        tracemalloc.reset_peak()
        t = time.process_time()
        try:
            return fn(unit)
        finally:
            log.append((time.process_time() - t, tracemalloc.get_traced_memory()[1]))
            tracemalloc.stop()
    return run


def arguments(description: str) -> argparse.Namespace:
    """The generated part's size and the report's sample from the command line (the usage in the module doc)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--tiles", type=int, default=3)
    ap.add_argument("--tile-mm", type=float, default=500.0)
    ap.add_argument("--width-mm", type=float, default=1500.0)
    ap.add_argument("--report-points", type=int, default=20_000)
    return ap.parse_args()


@dataclass(frozen=True)
class FlatPart:
    """The generated part in its scan store: its tiles, the dent's place (x, y, mm), the CAD surface and its file as
    the tiles' units read it (``tile_inspection.write_cad``, relative to ``store``)."""

    store: Path
    dent_mm: tuple[float, float]
    cloud: TiledCloud
    surface: CadSurface
    cad: str


@contextlib.contextmanager
def flat_part(args: argparse.Namespace, prefix: str) -> Iterator[FlatPart]:
    """The part of :func:`arguments`' size in a new temporary scan store, removed once the block is done."""
    store = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        dent = (1.37 * args.tile_mm, 0.47 * args.width_mm)
        cloud = generated_part(store, args.tiles, args.tile_mm, args.width_mm, dent)
        surface = CadSurface(o3d.io.read_triangle_mesh(str(flat_cad(store / "cad.ply", args.tiles * args.tile_mm,
                                                                    args.width_mm))))
        yield FlatPart(store, dent, cloud, surface, write_cad(store, surface))
    finally:
        shutil.rmtree(store, ignore_errors=True)


def main() -> None:
    args = arguments(__doc__.split("\n\n")[0])
    with flat_part(args, "tile-areas-") as part:
        store, dent, cloud = part.store, part.dent_mm, part.cloud
        inspect_log, area_log = [], []
        tile_inspection.inspect_tile = measured(tile_inspection.inspect_tile, inspect_log)
        tile_inspection.find_tile_areas = measured(tile_inspection.find_tile_areas, area_log)
        backend = LocalBackend(1)
        inspected = inspect_tiles(cloud.tiles, store, store / part.cad, np.eye(4), BOUNDS.lower_mm, BOUNDS.upper_mm,
                                  backend)
        areas = tile_areas(inspected, store, np.eye(4), BOUNDS, backend)
        sample = cloud.every_kth(-(-len(cloud) // args.report_points))
        in_sample = find_deviation_areas(DeviationCloud(sample.points_mm, sample.points_mm[:, 2]), BOUNDS.lower_mm,
                                         BOUNDS.upper_mm, BOUNDS.smoothing_mm, BOUNDS.min_area_mm2)

        def holds_dent(found) -> bool:
            return any(np.hypot(a.centroid_mm[0] - dent[0], a.centroid_mm[1] - dent[1]) < 3.0 for a in found)

        points = np.array([t.voxels for t in cloud.tiles], float)[[t.index for t in inspected]]
        per_unit = {name: {"cpu_s": [round(c, 2) for c, _ in log],
                           "traced_peak_bytes_per_point": [round(b / n) for (_, b), n in zip(log, points, strict=True)]}
                    for name, log in (("inspect", inspect_log), ("areas", area_log))}
        publish("tile_areas", {"tiles": len(cloud.tiles), "points": len(cloud), "points_per_tile": int(points.max()),
                               **per_unit, "tiles_find_dent": holds_dent(areas), "report_points": len(sample.points_mm),
                               "sample_finds_dent": holds_dent(in_sample)})


if __name__ == "__main__":
    main()

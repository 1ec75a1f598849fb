"""Alignment to CAD from random starts on generated parts of different kinds (sim_drivers/generated_parts.py:
``PARTS`` and a new customer's ``CUSTOMER_PARTS``):
the share of starts that align within 0.05 mm / 0.005 deg of the truth, the share that fail with a reason, those
whose alignment says its pose is ambiguous (a twin pose not ruled out) and those wrong without failing or saying so,
the errors and the seconds, per part, and the seeded defects found with their sign.

Usage: nice python benchmarks/alignment_starts.py [--starts 20] [--points 30000] [--max-deg 30] [--max-mm 300]
                                                 [--parts arch,...] [--publish NAME]

Each start turns the measured cloud by up to ``--max-deg`` about a random axis through the CAD origin and moves
it by up to ``--max-mm``; ``tandemscan inspect``'s path then aligns it from where it lies (``align``, with the
cloud's normals as a scanner writes them), orients the CAD by them and inspects it. Prints one JSON object on its
last line and keeps it as ``benchmarks/results/NAME.json`` (``--publish``). Timings on a shared CPU are
unreliable.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from clean_exit import clean_exit_on_sigterm
from results import publish
from tandemscan.config.models import InspectionConfig
from tandemscan.pipeline.geometry import frames as F
from tandemscan.pipeline.inspection.alignment import AlignmentCriteria, AlignmentFailed, align
from tandemscan.pipeline.inspection.inspect import CadSurface, InspectionCriteria, inspect_cloud
from tandemscan.pipeline.inspection.inspection_job import measured_side
from tandemscan.sim_drivers.generated_parts import CUSTOMER_PARTS, PARTS, GeneratedPart, random_misplacement
from tandemscan.sim_drivers.inspection_score import alignment_error

TARGET = (0.05, 0.005)  # mm, deg at the CAD's bounding-box centre
CFG = InspectionConfig(reference_spheres=(), regions=(), best_fit=False)
CRITERIA = InspectionCriteria.from_section(CFG)


def defects_found(part: GeneratedPart, areas) -> int:
    """Seeded defects with an area of their side within 10 mm and its extreme within 0.03 mm."""
    found = 0
    for d in part.defects:
        side = "upper" if d.depth_mm > 0 else "lower"
        near = [a for a in areas if np.linalg.norm(np.subtract(a.centroid_mm, d.centre_mm)) < 10.0]
        found += bool(near) and all(a.side == side for a in near) and abs(
            max(near, key=lambda a: abs(a.extreme_mm)).extreme_mm - d.depth_mm) <= 0.03
    return found


def one_part(name: str, args: argparse.Namespace) -> dict:
    part = {**PARTS, **CUSTOMER_PARTS}[name]()
    surface = CadSurface(part.mesh)
    rng = np.random.default_rng(args.seed)
    p_F, n_F = part.measured(args.points, args.noise_mm, rng)
    v = np.asarray(part.mesh.vertices)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    within, failed, wrong, silent, ambiguous, mm, deg, seconds, found, reasons = 0, 0, 0, 0, 0, [], [], [], 0, []
    for _ in range(args.starts):
        T_W_F = random_misplacement(rng, args.max_deg, args.max_mm)
        p_W = F.transform_points(T_W_F, p_F)
        t0 = time.perf_counter()
        try:
            a = align(surface, p_W, AlignmentCriteria.from_section(CFG), toward_W=F.rotate_vectors(T_W_F, n_F))
        except AlignmentFailed as e:
            seconds.append(time.perf_counter() - t0)
            failed += 1
            reasons.append(str(e))
            continue
        seconds.append(time.perf_counter() - t0)
        e_mm, e_deg = alignment_error(a.T_F_W, F.invert(T_W_F), centre)
        mm.append(e_mm)
        deg.append(e_deg)
        ok = e_mm <= TARGET[0] and e_deg <= TARGET[1]
        within += ok
        wrong += not ok
        ambiguous += bool(a.ambiguity)
        silent += not ok and not a.ambiguity
        if ok:
            oriented, _ = measured_side(surface, p_W, a.T_F_W, F.rotate_vectors(T_W_F, n_F), None)
            found += defects_found(part, inspect_cloud(F.transform_points(a.T_F_W, p_W), oriented, CRITERIA).areas)
    return {"points": len(p_F), "starts": args.starts, "aligned_within_target": within, "failed_with_reason": failed,
            "wrong_without_failing": wrong, "said_ambiguous": ambiguous, "wrong_without_saying": silent,
            "success_rate": round(within / args.starts, 3),
            "err_mm_max": round(max(mm), 5) if mm else None, "err_mm_median": round(float(np.median(mm)), 5)
            if mm else None, "err_deg_max": round(max(deg), 6) if deg else None,
            "defects_found": found, "defects_seeded": len(part.defects) * within,
            "seconds_median": round(float(np.median(seconds)), 2), "seconds_max": round(max(seconds), 2),
            "failures": reasons[:3]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--starts", type=int, default=20)
    ap.add_argument("--points", type=int, default=30_000)
    ap.add_argument("--noise-mm", type=float, default=0.01)
    ap.add_argument("--max-deg", type=float, default=30.0)
    ap.add_argument("--max-mm", type=float, default=300.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--parts", default=",".join(PARTS), help=f"of {', '.join([*PARTS, *CUSTOMER_PARTS])}")
    ap.add_argument("--publish", default="alignment_starts", metavar="NAME", help="benchmarks/results/NAME.json")
    args = ap.parse_args()
    out: dict = {"benchmark": "alignment_starts", "target": {"mm": TARGET[0], "deg": TARGET[1]},
                 "max_deg": args.max_deg, "max_mm": args.max_mm, "noise_mm": args.noise_mm}
    for name in args.parts.split(","):
        out[name] = one_part(name, args)
    starts = sum(out[n]["starts"] for n in args.parts.split(","))
    out["success_rate"] = round(sum(out[n]["aligned_within_target"] for n in args.parts.split(",")) / starts, 3)
    for key in ("wrong_without_failing", "said_ambiguous", "wrong_without_saying"):
        out[key] = sum(out[n][key] for n in args.parts.split(","))
    publish(args.publish, out)


if __name__ == "__main__":
    clean_exit_on_sigterm()
    main()

"""``tandemscan inspect CLOUD --cad MESH [--tolerance 0.1] [--out DIR] [--alignment best-fit|rps|none]``:
deviation report for any cloud, registered to CAD from where it lies.

``add_commands(subparsers)`` adds the sub-command to the main CLI; ``main(argv)`` runs it on its own.
Bad input ends with one clear error line on stderr and exit status 2; a cloud that cannot be aligned to the
CAD writes the report of a failed inspection (verdict "indeterminate", the reason) and ends with one line
``not completed:`` and exit status 5 (docs/cli.md, "Exit status"; docs/inspection-method.md, "Alignment").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tandemscan.config import ConfigError, load_config
from tandemscan.config.inspection_template import load_template
from tandemscan.pipeline.geometry.units import MM_PER_UNIT

EXIT_BAD_INPUT = 2
EXIT_NOT_INSPECTED = 5  # the alignment to CAD failed (docs/cli.md: not completed): report.html and report.json say why


def add_commands(subparsers) -> argparse.ArgumentParser:
    """Add the ``inspect`` sub-command to an argparse sub-parser collection."""
    p = subparsers.add_parser(
        "inspect",
        help="deviation of a point cloud from its CAD mesh: report.html, report.json, PLY with deviations",
        description="Signed deviation of CLOUD (mm, near the CAD frame) from MESH after aligning it to CAD (robust "
        "best fit, reference spheres or none), with the areas beyond the tolerance, a verdict, statistics, "
        "colour maps; writes report.html, report.json, figures/ and cloud_deviation.ply.",
    )
    configure(p)
    return p


def configure(p: argparse.ArgumentParser) -> None:
    """The sub-command's arguments."""
    p.add_argument("cloud", type=Path, help="point cloud file (.ply .pcd .xyz), millimetres, near the CAD frame")
    p.add_argument("--cad", type=Path, required=True, help="CAD mesh file (.stl .ply .obj), millimetres")
    p.add_argument("--tolerance", type=float, default=None, metavar="MM",
                   help="symmetric tolerance band +/- MM (default: the config's inspection band)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="output folder (default: out/inspect)")
    p.add_argument("--config", type=Path, default=None, help="cell configuration TOML (default: the sim cell)")
    p.add_argument("--alignment", choices=("best-fit", "rps", "none"), default=None,
                   help="registration to CAD: robust best fit, the reference spheres of [inspection] (RPS), or none "
                   "(the cloud is in the CAD frame); default: the config's")
    p.add_argument("--datum", action="append", default=None, metavar="REGION",
                   help="best fit on the points of this [inspection] region only (repeatable)")
    p.add_argument("--template", type=Path, default=None, metavar="T.toml",
                   help="inspection template: the part's characteristics and alignment (docs/inspection.md)")
    p.add_argument("--serial", default=None, help="the measured part's serial number (report, results.qif)")
    p.add_argument("--point-uncertainty-mm", type=float, default=None, metavar="U",
                   help="the cloud's own expanded uncertainty per point (k = [inspection] decision_k), mm; default: "
                   "the PLY's uncertainty_mm property where it has one, else 0")
    p.add_argument("--cad-units", choices=sorted(MM_PER_UNIT), default="mm", help="the unit of the CAD mesh file")
    p.add_argument("--cloud-units", choices=sorted(MM_PER_UNIT), default="mm", help="the unit of the cloud file")
    p.add_argument("--no-best-fit", action="store_true",
                   help="skip the separate best-fit figures reported after the alignment")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the inspection for parsed ``args``; 0 on success, 2 with one error line on bad input, 5 with one
    line where the cloud could not be aligned to the CAD."""
    from tandemscan.pipeline.inspection.inspect import InspectionError  # local: keep `tandemscan --help` fast
    from tandemscan.pipeline.inspection.inspection_job import InspectionSettings, inspect_files

    prog = "tandemscan inspect"
    try:
        cell = load_config(args.config)
        cfg = cell.inspection
        update = {}
        if args.tolerance is not None:
            if not args.tolerance > 0:
                raise InspectionError(f"--tolerance must be > 0 mm, got {args.tolerance}")
            update |= {"tolerance_lower_mm": -args.tolerance, "tolerance_upper_mm": args.tolerance}
        if args.no_best_fit:
            update["best_fit"] = False
        if args.alignment is not None:
            update["alignment"] = args.alignment
        if args.datum:
            update["datum_regions"] = tuple(args.datum)
        cfg = cfg.model_copy(update=update)
        out = args.out if args.out is not None else cell.job.out_dir / "inspect"
        template = None if args.template is None else load_template(args.template)
        part = {k: v for k, v in (("part_number", template.part_number if template else None),
                                  ("serial", args.serial), ("template", args.template and str(args.template)),
                                  ("measuring_system", f"the scanner of {args.cloud.name} (tandemscan inspect)"))
                if v is not None}
        if args.point_uncertainty_mm is not None and not args.point_uncertainty_mm >= 0:
            raise InspectionError(f"--point-uncertainty-mm must be >= 0 mm, got {args.point_uncertainty_mm}")
        settings = InspectionSettings.from_section(cfg, template)
        outputs = inspect_files(args.cloud, args.cad, out, settings, template, part, args.point_uncertainty_mm,
                                (args.cad_units, args.cloud_units))
    except (InspectionError, ConfigError, OSError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if outputs.result is None:
        print(f"{prog}: not completed: {outputs.data['reason']}; the report says why: {outputs.html}", file=sys.stderr)
        return EXIT_NOT_INSPECTED
    s, t, a = outputs.result.stats, outputs.result.tolerance, outputs.data["alignment"]
    print(
        f"{outputs.result.verdict.upper()}: {len(outputs.result.areas)} areas beyond the band; aligned by "
        f"{a['method']} (residual {a['residual_mm']:.4f} mm)\n"
        f"{s.count} points: mean {s.mean_mm:+.4f} mm, sigma {s.sigma_mm:.4f} mm, RMS {s.rms_mm:.4f} mm, "
        f"{t.in_pct:.2f} % within [{t.lower_mm:+.3f}, {t.upper_mm:+.3f}] mm\n"
        f"report: {outputs.html}\ndata:   {outputs.json}\ncloud:  {outputs.ply}"
    )
    if a.get("free_directions"):
        print(f"not fixed by the measured surface (held where the cloud was given): {'; '.join(a['free_directions'])}")
    if a.get("ambiguity"):
        print(f"pose not proven: {a['ambiguity']}")
    if outputs.qif is not None:
        print(f"QIF:    {outputs.qif}")
    for c in outputs.characteristics:
        print(f"{c.id:>10} {c.status.upper():<13} actual {c.actual_mm:+.3f} mm in "
              f"[{c.lower_mm:+.3f}, {c.upper_mm:+.3f}] U {c.uncertainty_mm:.3f}  {c.name}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry: ``python -m tandemscan.daemon.cli.inspect_cmd CLOUD --cad MESH``."""
    parser = argparse.ArgumentParser(prog="tandemscan inspect")
    configure(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())

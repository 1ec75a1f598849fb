"""A finished job's report as the end of the job returned it (``JobResult.report``): its ``report.json`` with the
simulator's observer's ``ground_truth.json`` joined in, where the observer scored the job (docs/end-of-job.md).
The product writes the two files apart and reads neither back; the tests join them to compare with the model."""

from __future__ import annotations

import json
from pathlib import Path

from tandemscan.pipeline.job_report import GROUND_TRUTH_FILE, REPORT_FILE


def joined_report(report: dict, ground_truth: dict | None) -> dict:
    """``report.json``'s content with ``ground_truth.json``'s (None: a job no observer scored) where
    ``JobReport.to_json`` puts the observer's scores: the ``ground_truth`` section, and the tracker-only stitch's
    summary as the correction's ``before``."""
    if ground_truth is None:
        return report
    before = {"before": ground_truth["before"]} if "before" in ground_truth else {}
    return report | {"correction": report["correction"] | before, "ground_truth": ground_truth["ground_truth"]}


def report_with_ground_truth(job_dir: Path | str) -> dict:
    """The report of the job in ``job_dir`` from its files: ``report.json`` and, where it is there,
    ``ground_truth.json`` (:func:`joined_report`)."""
    truth = Path(job_dir) / GROUND_TRUTH_FILE
    return joined_report(json.loads((Path(job_dir) / REPORT_FILE).read_text(encoding="utf-8")),
                         json.loads(truth.read_text(encoding="utf-8")) if truth.is_file() else None)

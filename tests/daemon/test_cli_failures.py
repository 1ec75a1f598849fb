"""Every failure of ``measure``, ``calibrate``, ``plan`` and ``inspect`` ends in one line and its documented exit
status (docs/cli.md, "Exit status"), never a traceback: each command is run into each device fault the
simulated cell injects (``[sim] fault_*``: a scanner timeout, an e-stop, an arm servo fault, a tracker that stops
answering) and into each kind of bad file; the background workers of a failed job stop with the command."""

from __future__ import annotations

import json
import multiprocessing
import threading
from pathlib import Path

import pytest
from tandemscan.config.loader import default_config_path
from tandemscan.daemon import cli
from tandemscan.daemon.cli import command, plan_cmd

SHIPPED = default_config_path().read_text(encoding="utf-8")


#: a calibration job of four plate views (the shipped 32): the faults below come within its first views, and
#: planning fewer views keeps each command short
FEW_VIEWS = "\n[calibration]\nposes = 4\n"


def cell_toml(folder: Path, name: str, sim: str = "", tracker: str = "", extra: str = "") -> Path:
    """The shipped simulated cell with ``sim`` lines added to its ``[sim]`` and ``tracker`` to its ``[tracker]``,
    ``extra`` (whole tables) at its end."""
    text = SHIPPED.replace("[sim]\n", f"[sim]\n{sim}\n").replace("[tracker]\n", f"[tracker]\n{tracker}\n") + extra
    path = folder / f"{name}.toml"
    path.write_text(text, encoding="utf-8")
    return path


def run_cli(argv: list[str], capfd) -> tuple[int, list[str]]:
    """Exit status and the lines on stderr that are not the progress bar."""
    status = cli.main(argv)
    err = capfd.readouterr().err
    assert "Traceback" not in err, err
    return status, [ln for ln in err.splitlines() if ln.strip() and "━" not in ln]


def one_line(lines: list[str], label: str) -> str:
    (line,) = [ln for ln in lines if ln.startswith(f"{label}:")]
    return line


FAULTS = {  # [sim] line -> the device's words in the one line
    "scanner timeout": ("fault_scanner_timeout_every = 3", "scanner: no frame within the capture timeout"),
    "arm servo fault": ("fault_arm_after_moves = 3", "arm: servo fault"),
    "tracker stops answering": ("fault_tracker_after_frames = 3", "tracker: no pose within the timeout"),
}


@pytest.mark.parametrize("fault", FAULTS)
def test_measure_into_a_device_fault_is_one_line_exit_4_and_its_workers_stop(fault, tmp_path, capfd):
    sim, words = FAULTS[fault]
    threads = set(threading.enumerate())
    status, lines = run_cli(["measure", "--config", str(cell_toml(tmp_path, "cell", sim)), "--out",
                             str(tmp_path / "out")], capfd)
    assert status == command.EXIT_DEVICE_FAULT == 4
    line = one_line(lines, "device fault")
    assert words in line and "scans measured so far are in" in line
    # the pair registration's process (started at the first scan) is gone, the threads of the job end promptly
    assert multiprocessing.active_children() == []
    left = [t for t in threading.enumerate() if t not in threads and not t.daemon]
    for t in left:
        t.join(5.0)
    assert [t for t in left if t.is_alive()] == []


def test_measure_into_an_estop_is_one_line_exit_3(tmp_path, capfd):
    status, lines = run_cli(["measure", "--config", str(cell_toml(tmp_path, "cell", "fault_estop_after_moves = 1")),
                             "--out", str(tmp_path / "out")], capfd)
    assert status == command.EXIT_SAFETY_STOP == 3
    assert "scans measured so far are in" in one_line(lines, "safety stop")


@pytest.mark.slow
@pytest.mark.parametrize("fault", FAULTS)
def test_calibrate_into_a_device_fault_is_one_line_exit_4(fault, tmp_path, capfd):
    sim, words = FAULTS[fault]
    out = tmp_path / "calibration.json"
    status, lines = run_cli(["calibrate", "--config", str(cell_toml(tmp_path, "cell", sim, extra=FEW_VIEWS)),
                             "--out", str(out)], capfd)
    assert status == command.EXIT_DEVICE_FAULT
    line = one_line(lines, "device fault")
    assert words in line and f"no calibration written to {out}" in line and not out.exists()


@pytest.mark.slow
def test_calibrate_that_sees_no_plate_is_not_completed_exit_5(tmp_path, capfd):
    out = tmp_path / "calibration.json"
    toml = cell_toml(tmp_path, "short-sighted", tracker="target_view_cone_deg = 1.0", extra=FEW_VIEWS)
    status, lines = run_cli(["calibrate", "--config", str(toml), "--out", str(out)], capfd)
    assert status == command.EXIT_NOT_COMPLETED == 5
    assert "usable plate views" in one_line(lines, "not completed") and not out.exists()


@pytest.fixture
def bad_files(tmp_path) -> dict[str, Path]:
    """One of each kind of bad file: missing, not the format, the right format with the wrong content, and a
    file where a folder must be."""
    files = {name: tmp_path / file for name, file in (
        ("missing", "missing.toml"), ("garbage", "garbage.toml"), ("invalid", "invalid.toml"),
        ("wrong_json", "wrong.json"), ("garbage_mesh", "garbage.stl"), ("garbage_cloud", "garbage.ply"),
        ("a_file", "a-file"))}
    files["garbage"].write_text("this is [not toml\n")
    files["invalid"].write_text("[scanner]\nnoise_sigma_mm = -1\n")
    files["wrong_json"].write_text('{"T_V1_C": [1, 2]}')
    files["garbage_mesh"].write_bytes(b"solid nothing\nendsolid\n")
    files["garbage_cloud"].write_bytes(b"ply\nformat nonsense\n")
    files["a_file"].write_text("x")
    return files


BAD_INPUT = {  # command line with {placeholders} of bad_files -> words in the line
    "measure: missing config": ("measure --config {missing}", "file not found"),
    "measure: garbage config": ("measure --config {garbage}", "not valid TOML"),
    "measure: invalid config": ("measure --config {invalid}", "noise_sigma_mm"),
    "measure: missing calibration": ("measure --calibration {missing}", "no calibration file at"),
    "measure: wrong calibration": ("measure --calibration {wrong_json}", "not a calibration"),
    "measure: missing plan": ("measure --plan {missing}", "file not found"),
    "measure: garbage plan": ("measure --plan {garbage}", "not valid TOML"),
    "measure: missing part": ("measure --part {missing}", "missing.toml"),
    "measure: garbage part": ("measure --part {garbage_mesh}", "garbage.stl"),
    "measure: output under a file": ("measure --out {a_file}/out", "a-file"),
    "calibrate: missing config": ("calibrate --config {missing}", "file not found"),
    "calibrate: output under a file": ("calibrate --out {a_file}/calibration.json", "a-file"),
    "plan: missing part": ("plan --part {missing}", "missing.toml"),
    "plan: garbage part": ("plan --part {garbage_mesh}", "garbage.stl"),
    "plan: invalid config": ("plan --config {invalid}", "noise_sigma_mm"),
    "plan: output under a file": ("plan --out {a_file}/plan.toml", "a-file"),
    "inspect: missing cloud": ("inspect {missing} --cad {garbage_mesh}", "missing.toml"),
    "inspect: garbage cloud": ("inspect {garbage_cloud} --cad {garbage_mesh}", "garbage.ply"),
    "inspect: invalid config": ("inspect {garbage_cloud} --cad {garbage_mesh} --config {invalid}", "noise_sigma_mm"),
}


@pytest.mark.parametrize("case", BAD_INPUT)
def test_bad_input_is_one_line_exit_2(case, bad_files, tmp_path, capfd, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the default outputs (out/) land here
    template, words = BAD_INPUT[case]
    status, lines = run_cli(template.format(**bad_files).split(), capfd)
    assert status == command.EXIT_USAGE == 2
    errors = [ln for ln in lines if "error:" in ln]
    assert len(errors) == 1 and words in errors[0], lines


def test_a_defect_is_one_line_exit_70(monkeypatch, capfd):
    def broken(args):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(plan_cmd, "cmd_plan", broken)
    status, lines = run_cli(["plan"], capfd)
    assert status == command.EXIT_INTERNAL == 70
    assert "ZeroDivisionError: a bug" in one_line(lines, "internal error")


def test_measure_says_its_mounts_on_its_first_line_and_warns_on_nominal_ones(tmp_path, capfd):
    """Run into an early arm fault (only the first line matters): nominal mounts are said with a warning that the
    cell is not calibrated; a calibration file is named with the mounts it calibrated."""
    from tandemscan.config import load_config
    from tandemscan.pipeline.stitching.installation import Installation

    toml = str(cell_toml(tmp_path, "cell", "fault_arm_after_moves = 1"))
    assert cli.main(["measure", "--config", toml, "--out", str(tmp_path / "out")]) == command.EXIT_DEVICE_FAULT
    first = capfd.readouterr().out.splitlines()[0]
    assert first.startswith("mounts: nominal") and "warning: the cell is not calibrated" in first
    calibration = tmp_path / "calibration.json"
    sources = {"T_T_S": "hand-eye (park, 12 poses)", "T_E_S": "nominal", "T_V1_C": "turns in place",
               "T_V2_B": "nominal"}
    calibration.write_text(json.dumps({**Installation.nominal(load_config().installation).to_json(),
                                       "sources": sources}))
    assert cli.main(["measure", "--config", toml, "--calibration", str(calibration), "--out",
                     str(tmp_path / "out")]) == command.EXIT_DEVICE_FAULT
    first = capfd.readouterr().out.splitlines()[0]
    assert first == f"mounts: calibration file {calibration}; calibrated T_T_S, T_V1_C, nominal T_E_S, T_V2_B"

"""The console's routes without a browser: what is public and what needs the token, the safety read-out, the
plan's top view and the thinned binary cloud (docs/console.md).

The runner here is a stand-in that waits for the test, then writes what a finished job leaves behind
(``report.json`` with its inspection section and ``cloud_deviation.ply``), so the view endpoint reads files of
the real layout without running a measurement.
"""

from __future__ import annotations

import asyncio
import json
import struct

import httpx
import numpy as np
import pytest
from serving import running_server
from tandemscan.daemon.api.app import create_app
from tandemscan.daemon.api.console.cloud_view import DEVIATION_COLOURS, VIEW_FILE, CloudViewError, view_file
from tandemscan.daemon.api.console.router import ASSETS, plan_view
from tandemscan.daemon.cell.devices import build_cell
from tandemscan.daemon.plans import PlanCatalog
from tandemscan.daemon.service import Daemon
from tandemscan.pipeline.io.export import write_ply
from tandemscan.pipeline.planning.plan import MoveMeasure, MoveTracker, Scan
from tandemscan.sim_drivers.cell import Simulation
from tandemscan.sim_drivers.world import SimWorld

TOKEN = "console-api-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SCALE_MM, TOLERANCE_MM = (-0.3, 0.3), (-0.1, 0.1)


def parse_view(data: bytes) -> tuple[dict, np.ndarray, np.ndarray | None]:
    """(header, points + origin (n, 3) mm, deviations) of the layout docs/console.md gives."""
    assert data[:4] == b"TSV1"
    (length,) = struct.unpack_from("<I", data, 4)
    assert length % 4 == 0
    header = json.loads(data[8:8 + length])
    n = header["points"]
    xyz = np.frombuffer(data, "<f4", 3 * n, 8 + length).reshape(n, 3) + np.array(header["origin_mm"])
    deviation = np.frombuffer(data, "<f4", n, 8 + length + 12 * n) if header["deviation"] else None
    assert len(data) == 8 + length + (16 if header["deviation"] else 12) * n
    return header, xyz, deviation


def write_inspected_job(job_dir, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A finished, inspected job's files: cloud_deviation.ply (frame F) and report.json; returns both fields."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([-1500, 0, 0], [1500, 2000, 1200], (n, 3))
    deviation = rng.normal(0.0, 0.05, n)
    write_ply(job_dir / "cloud_deviation.ply", points, rng.normal(size=(n, 3)), {"deviation_mm": deviation})
    write_ply(job_dir / "cloud.ply", points[::2] - 5.0)
    report = {"inspection": {"colour_scale_mm": list(SCALE_MM), "files": {"deviation_ply": "cloud_deviation.ply"},
                             "as_measured": {"tolerance": {"lower_mm": TOLERANCE_MM[0], "upper_mm": TOLERANCE_MM[1],
                                                           "in_pct": 95.0, "above_pct": 2.5, "below_pct": 2.5}},
                             "verdict": "fail", "alignment": {"method": "rps", "residual_mm": 0.004},
                             "deviations": [{"id": 1, "side": "lower", "centroid_mm": [10.0, 20.0, 30.0],
                                             "area_mm2": 1200.0, "extreme_mm": -0.31, "mean_mm": -0.18,
                                             "points": 900}]}}
    (job_dir / "report.json").write_text(json.dumps(report), encoding="utf-8")
    return points, deviation


class ReleasedRunner:
    """Holds each job until :meth:`release`, then writes an inspected job's files and succeeds."""

    def __init__(self):
        self.go = asyncio.Event()

    def release(self) -> None:
        self.go.set()

    async def __call__(self, ctx) -> dict:
        await self.go.wait()
        await asyncio.to_thread(write_inspected_job, ctx.store.job_dir(ctx.job.id), 5000)
        return {"scans": 1}


@pytest.fixture
async def api(tmp_path, sim_config):
    world = SimWorld(sim_config)
    runner = ReleasedRunner()
    cell = build_cell(sim_config, simulation=Simulation(sim_config, world=world))
    daemon = Daemon(sim_config, tmp_path / "state", runner, token=TOKEN, cell=cell)
    async with running_server(create_app(daemon, manage_lifecycle=True)) as url:
        async with httpx.AsyncClient(base_url=url, timeout=10) as client:
            client.runner, client.world, client.daemon = runner, world, daemon
            yield client


def assert_problem(r, status):
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    return r.json()


async def wait_for(predicate, timeout_s: float = 10.0):
    for _ in range(int(timeout_s / 0.02)):
        if value := await predicate():
            return value
        await asyncio.sleep(0.02)
    raise AssertionError("condition not met in time")


async def test_the_page_is_public_and_the_console_data_needs_the_token(api):
    page = await api.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    for name, media_type in ASSETS.items():
        assert f"/console/{name}" in page.text
        r = await api.get(f"/console/{name}")
        assert r.status_code == 200 and r.headers["content-type"].startswith(media_type) and len(r.text) > 500
    assert "no-such.js" in assert_problem(await api.get("/console/no-such.js"), 404)["detail"]
    job = (await api.post("/v1/jobs", json={}, headers=AUTH)).json()
    for path in ("/v1/session", "/v1/safety", f"/v1/jobs/{job['id']}/plan", f"/v1/jobs/{job['id']}/view"):
        r = await api.get(path)
        assert_problem(r, 401)
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert_problem(await api.get(path, headers={"Authorization": "Bearer wrong"}), 401)
    assert (await api.get("/v1/session", headers=AUTH)).json() == {"token_required": True,
                                                                  "version": api.daemon.version}
    api.runner.release()


async def test_openapi_lists_the_console_routes_with_their_401(api):
    spec = (await api.get("/openapi.json")).json()
    for path in ("/", "/console/{name}"):
        assert "get" in spec["paths"][path]
    for path in ("/v1/session", "/v1/safety", "/v1/jobs/{job_id}/plan", "/v1/jobs/{job_id}/view"):
        assert "401" in spec["paths"][path]["get"]["responses"], path


async def test_safety_read_out_says_when_a_reset_is_allowed(api):
    now = (await api.get("/v1/safety", headers=AUTH)).json()
    assert now == {"latched": False, "reason": None, "inputs_readable": True, "estop": False,
                   "light_curtain_broken": False, "reset_allowed": True}
    api.world.safety.light_curtain_broken = True

    async def latched():
        body = (await api.get("/v1/safety", headers=AUTH)).json()
        return body if body["latched"] else None

    body = await wait_for(latched)
    assert body["light_curtain_broken"] and not body["reset_allowed"] and body["reason"] == "light curtain broken"
    assert_problem(await api.post("/v1/safety/reset", headers=AUTH), 409)
    api.world.safety.light_curtain_broken = False
    body = (await api.get("/v1/safety", headers=AUTH)).json()
    assert body["latched"] and body["reset_allowed"]
    assert (await api.post("/v1/safety/reset", headers=AUTH)).json()["safety"]["latched"] is False


def test_plan_view_of_the_shipped_band_plan():
    plan = PlanCatalog([PlanCatalog.shipped_folder()]).get("default-band")
    view = plan_view(plan, {"measure": "measure_chassis", "tracking": "tracking_chassis"})
    assert view.steps_total == len(view.step_labels) == len(plan.steps) == 39
    measure = [s for s in view.stations if s.robot == "measure"]
    tracking = [s for s in view.stations if s.robot == "tracking"]
    assert len(measure) == 3 and len(tracking) == 2 and not any(s.scan_steps for s in tracking)
    scans = [i for s in measure for i in s.scan_steps]
    assert scans == [i for i, s in enumerate(plan.steps) if isinstance(s, Scan)]  # each scan once, in order
    for s in view.stations:
        step = plan.steps[s.step]
        assert isinstance(step, MoveMeasure if s.robot == "measure" else MoveTracker)
        assert (s.x_mm, s.y_mm, s.heading_rad) == (step.x_mm, step.y_mm, step.heading_rad)
        # a station's scans come after it and before the same AGV's next station
        assert all(i > s.step for i in s.scan_steps)
    assert view.step_labels[scans[0]].startswith("scan: station 0")


def test_cloud_view_thins_to_200k_keeps_deviations_and_the_report_scale(tmp_path):
    points, deviation = write_inspected_job(tmp_path, 450_001)
    data = view_file(tmp_path).read_bytes()
    header, xyz, dev = parse_view(data)
    keep = slice(None, None, 3)  # ceil(450001 / 200000)
    assert header["frame"] == "F" and header["points_total"] == 450_001 and header["points"] == len(points[keep])
    np.testing.assert_allclose(xyz, points[keep], atol=1e-3)  # float32 about the centre: well under a micron
    np.testing.assert_array_equal(dev, deviation[keep].astype(np.float32))
    assert header["colour_scale_mm"] == list(SCALE_MM) and header["tolerance_mm"] == list(TOLERANCE_MM)
    assert (tmp_path / VIEW_FILE).read_bytes() == data  # cached for the next request


def test_cloud_view_colours_are_the_reports_colour_map():
    from matplotlib.colors import to_rgb
    from tandemscan.pipeline.inspection.deviation_maps import DEVIATION_CMAP

    stops = DEVIATION_CMAP.resampled(len(DEVIATION_COLOURS))  # the map's colours at its evenly spaced stops
    for k, hex_colour in enumerate(DEVIATION_COLOURS):
        np.testing.assert_allclose(stops(k)[:3], to_rgb(hex_colour), atol=1e-6)


def test_cloud_view_without_inspection_is_the_world_cloud_without_deviations(tmp_path):
    points, _ = write_inspected_job(tmp_path, 1000)
    (tmp_path / "report.json").write_text(json.dumps({"inspection": {"skipped": "no registration"}}))
    header, xyz, dev = parse_view(view_file(tmp_path).read_bytes())
    assert header["frame"] == "W" and dev is None and header["colour_scale_mm"] is None
    np.testing.assert_allclose(xyz, points[::2] - 5.0, atol=1e-3)


def test_cloud_view_of_a_damaged_cloud_file_is_an_error_that_names_it(tmp_path):
    write_inspected_job(tmp_path, 1000)
    (tmp_path / "report.json").write_text(json.dumps({"inspection": {"skipped": "no registration"}}))
    cloud = tmp_path / "cloud.ply"
    cloud.write_bytes(cloud.read_bytes()[:-100])  # cut short, as by a full disk
    with pytest.raises(CloudViewError, match=r"cloud\.ply: truncated: \d+ of 500 vertices"):
        view_file(tmp_path)
    assert not (tmp_path / VIEW_FILE).exists()


async def test_view_and_plan_of_a_job_over_rest(api):
    job = (await api.post("/v1/jobs", json={}, headers=AUTH)).json()

    async def running():
        return (await api.get(f"/v1/jobs/{job['id']}")).json()["state"] == "running"

    await wait_for(running)
    assert "running" in assert_problem(await api.get(f"/v1/jobs/{job['id']}/view", headers=AUTH), 409)["detail"]
    plan = (await api.get(f"/v1/jobs/{job['id']}/plan", headers=AUTH)).json()
    assert plan["plan"] == "default-band" and len(plan["stations"]) == 5
    assert plan["chassis_devices"] == {"measure": "measure_chassis", "tracking": "tracking_chassis"}
    api.runner.release()

    async def succeeded():
        return (await api.get(f"/v1/jobs/{job['id']}")).json()["state"] == "succeeded"

    await wait_for(succeeded)
    # what the console's verdict reads: the inspection's verdict, its deviation areas and the alignment
    inspection = (await api.get(f"/v1/jobs/{job['id']}/report", headers=AUTH)).json()["inspection"]
    assert inspection["verdict"] == "fail" and inspection["alignment"]["method"] == "rps"
    assert [(a["side"], a["extreme_mm"]) for a in inspection["deviations"]] == [("lower", -0.31)]
    r = await api.get(f"/v1/jobs/{job['id']}/view", headers=AUTH)
    assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
    header, xyz, dev = parse_view(r.content)
    assert header["points"] == 5000 and dev is not None and np.isfinite(xyz).all()
    assert_problem(await api.get("/v1/jobs/nope/view", headers=AUTH), 404)

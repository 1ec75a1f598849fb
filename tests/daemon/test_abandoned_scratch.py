"""A job abandoned (failed, cancelled) by the daemon leaves no scratch files (daemon/jobs/journal.py): also where it is
cancelled after a crash without its runner up again, whose map process could not clean up."""

from __future__ import annotations

from tandemscan.daemon.jobs.journal import journaled_abandon
from tandemscan.daemon.plans import default_plan_path
from tandemscan.daemon.store.job_store import JobStore
from tandemscan.pipeline.planning.plan import Plan


async def test_a_job_cancelled_after_a_crash_without_its_runner_leaves_no_scratch_files(sim_config, tmp_path):
    """The crash left the end's scratch files in the job folder (the scan store): the scans prepared for the joint
    refinement, a shard of the tiled merge and the thinned copies. The manager abandons the recovered job without
    starting its runner (``JobManager.cancel``): they are removed, the raw scans kept."""
    store = JobStore(tmp_path / "state")
    try:
        plan = Plan.load(default_plan_path())
        job, _ = store.create_job(plan.name, {"plan": plan.model_dump(mode="json")}, len(plan.steps))
        job_dir = store.job_dir(job.id)
        for file in ("scans/scan-0000.npz", "joint/prepared.npz", "tiles/shards-0/0.npz", "thinned/scan-0000.npz"):
            (job_dir / file).parent.mkdir(parents=True, exist_ok=True)
            (job_dir / file).write_bytes(b"written before the crash")
        await journaled_abandon(None, sim_config)(store.get_job(job.id), store)  # no transfer to undo: no motion
    finally:
        store.close()
    assert sorted(p.relative_to(job_dir).as_posix() for p in job_dir.rglob("*")) == ["scans", "scans/scan-0000.npz"]

"""Results after OPC 40001-101 Machinery Result Transfer: a completed job is a result (its id the job id; one
``succeeded_with_gaps`` is ``IsPartial``), its
metadata a ``ResultMetaDataType`` (job, plan, part number, serial, verdict, times), and its file read through
the temporary file transfer: ``GenerateFileForRead`` opens a ``FileType`` object under ``ResultTransfer`` for
reading, the client reads it with ``Read`` and ends with ``Close``, which removes the object (docs/opcua.md).

The file of a result is :func:`result_file_name`: ``results.qif`` where the job wrote one, else ``report.json``,
the bytes REST serves. Every read of the journal and the job folder runs off the event loop (the facade's store
thread, asyncio's thread pool).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from asyncua import Node, Server, ua
from tandemscan.daemon.api.facade import ServiceFacade
from tandemscan.daemon.api.opcua.calls import CallRefused, spec_method
from tandemscan.daemon.api.opcua.model import CellNodes
from tandemscan.daemon.job_state import COMPLETED_STATES, JobState
from tandemscan.daemon.store.job_store import JobRecord

log = logging.getLogger(__name__)

QIF_FILE, REPORT_FILE = "results.qif", "report.json"
#: temporary file objects open at once; opening one more closes the oldest (a client that went away)
MAX_OPEN_FILES = 16
#: longest single Read (bytes)
MAX_READ = 1 << 20
_EVALUATION = {"pass": 1, "fail": 2}  # ResultEvaluationEnum: OK, NotOK; anything else NotDecidable (3)


def result_file_name(job_dir: Path) -> str:
    """The file of a job's result: ``results.qif`` where there is one, else ``report.json``."""
    return QIF_FILE if (job_dir / QIF_FILE).is_file() else REPORT_FILE


@dataclass(frozen=True)
class ResultFile:
    """A job's result file: its name and bytes."""

    name: str
    data: bytes


def _ts(t_s: float | None) -> datetime:
    return datetime.fromtimestamp(t_s or 0.0, UTC)


def verdict_of(report: dict) -> str | None:
    """The inspection's verdict a report gives ("pass", "fail"), None where it has none."""
    inspection = report.get("inspection")
    verdict = inspection.get("verdict") if isinstance(inspection, dict) else None
    return verdict if isinstance(verdict, str) else None


class ResultCatalog:
    """The results as OPC UA values, read through the service facade."""

    def __init__(self, facade: ServiceFacade, simulated: bool):
        self.facade = facade
        self.simulated = simulated

    def _job_dir(self, job_id: str) -> Path:
        return self.facade.job_dir(job_id)

    def _completed(self, job_id: str) -> JobRecord:
        """(store thread) The job of result ``job_id``; refused unless it completed (with gaps or without)."""
        job = self.facade.daemon.manager.get(job_id)
        if job.state not in COMPLETED_STATES:
            raise CallRefused(ua.StatusCodes.BadNotFound, f"job {job_id} is {job.state}: no result (yet)")
        return job

    def _metadata(self, job: JobRecord) -> ua.ExtensionObject:
        """(thread) ``ResultDataType`` of a completed job, its verdict read from its report."""
        job_dir = self._job_dir(job.id)
        name = result_file_name(job_dir)
        try:
            verdict = verdict_of(json.loads((job_dir / REPORT_FILE).read_text(encoding="utf-8")))
        except (OSError, ValueError):
            verdict = None
        meta = ua.ResultMetaDataType(
            ResultId=job.id, HasTransferableDataOnFile=(job_dir / name).is_file(),
            IsPartial=job.state == JobState.SUCCEEDED_WITH_GAPS,
            IsSimulated=self.simulated, ResultState=1, PartId=job.plan.get("serial_number") or "",
            ProductId=job.plan.get("part_number") or "", InternalRecipeId=job.plan_name, JobId=job.id,
            CreationTime=_ts(job.finished_s),
            ProcessingTimes=ua.ProcessingTimesDataType(StartTime=_ts(job.started_s), EndTime=_ts(job.finished_s)),
            ResultUri=f"/v1/jobs/{job.id}/{'report' if name == REPORT_FILE else 'files/' + name}",
            ResultEvaluation=ua.ResultEvaluationEnum(_EVALUATION.get(verdict, 3) if verdict else 0),
            ResultEvaluationDetails=ua.LocalizedText(f"verdict: {verdict}" if verdict else "no inspection verdict"),
            FileFormat="QIF" if name == QIF_FILE else "JSON")
        return ua.ResultDataType(ResultMetaData=meta)

    async def result(self, job_id: str) -> ua.ExtensionObject:
        """The ``ResultDataType`` of job ``job_id`` (refused unless it completed)."""
        job = await self.facade.read(self._completed, job_id)
        return await asyncio.to_thread(self._metadata, job)

    def _ids(self, limit: int) -> list[str]:
        """(store thread) Ids of the completed jobs, newest first, at most ``limit`` (0: all)."""
        jobs, _ = self.facade.daemon.store.list_jobs(sorted(COMPLETED_STATES), limit=limit or 2**31, offset=0)
        return [j.id for j in jobs]

    async def ids(self, limit: int = 0) -> list[str]:
        return await self.facade.read(self._ids, limit)

    async def latest(self) -> ua.ExtensionObject:
        ids = await self.ids(1)
        if not ids:
            raise CallRefused(ua.StatusCodes.BadNoData, "no job has completed yet")
        return await self.result(ids[0])

    async def file(self, job_id: str) -> ResultFile:
        """The bytes of the job's result file (refused unless it completed and the file is there)."""
        await self.facade.read(self._completed, job_id)
        name = await asyncio.to_thread(result_file_name, self._job_dir(job_id))
        return ResultFile(name, await self.facade.read_job_file(job_id, name))


@dataclass
class OpenFile:
    """A temporary ``FileType`` object open for reading."""

    node: Node
    handle: int
    data: bytes
    position: int = 0


class FileTransfer:
    """Temporary file objects under ``ResultTransfer``: made by :meth:`generate_for_read`, removed at Close."""

    def __init__(self, server: Server, nodes: CellNodes):
        self.server, self.nodes = server, nodes
        self._handles = itertools.count(1)
        self._open: dict[int, OpenFile] = {}

    async def generate_for_read(self, result: ResultFile) -> OpenFile:
        """A new file object holding ``result``, open for reading under a new handle."""
        while len(self._open) >= MAX_OPEN_FILES:
            await self.close(next(iter(self._open)))
        handle = next(self._handles)
        ns = self.nodes.ns
        node = await self.nodes.result_transfer.add_object(
            ua.NodeId(f"ResultManagement.ResultTransfer.File{handle}", ns),
            ua.QualifiedName(f"{handle}:{result.name}", ns), objecttype=ua.ObjectIds.FileType)
        f = OpenFile(node, handle, result.data)
        self._open[handle] = f
        for child in await node.get_children():
            name = (await child.read_browse_name()).Name
            if name == "Size":
                await child.write_value(ua.Variant(len(result.data), ua.VariantType.UInt64))
            elif name == "OpenCount":
                await child.write_value(ua.Variant(1, ua.VariantType.UInt16))
            elif name == "MimeType":
                await child.write_value(ua.Variant("application/xml" if result.name.endswith(".qif")
                                                   else "application/json", ua.VariantType.String))
            elif name in _FILE_METHODS:
                self.server.link_method(child, _FILE_METHODS[name](self, handle))
        return f

    def opened(self, handle: int, file_handle) -> OpenFile:
        """The open file ``file_handle`` names when it is this object's (``handle``); else refused."""
        f = self._open.get(handle)
        if f is None or file_handle != handle:
            raise CallRefused(ua.StatusCodes.BadInvalidArgument, f"file handle {file_handle} is not open here")
        return f

    async def close(self, handle: int) -> None:
        f = self._open.pop(handle, None)
        if f is not None:
            await self.server.delete_nodes([f.node], recursive=True)

    async def close_all(self) -> None:
        for handle in list(self._open):
            await self.close(handle)


def _read(transfer: FileTransfer, handle: int):
    async def read(file_handle: int, length: int) -> list[ua.Variant]:
        f = transfer.opened(handle, file_handle)
        chunk = f.data[f.position:f.position + max(0, min(length, MAX_READ))]
        f.position += len(chunk)
        return [ua.Variant(chunk, ua.VariantType.ByteString)]
    return spec_method([ua.VariantType.UInt32, ua.VariantType.Int32], read)


def _close(transfer: FileTransfer, handle: int):
    async def close(file_handle: int) -> list[ua.Variant]:
        transfer.opened(handle, file_handle)
        await transfer.close(handle)
        return []
    return spec_method([ua.VariantType.UInt32], close)


def _get_position(transfer: FileTransfer, handle: int):
    async def get_position(file_handle: int) -> list[ua.Variant]:
        return [ua.Variant(transfer.opened(handle, file_handle).position, ua.VariantType.UInt64)]
    return spec_method([ua.VariantType.UInt32], get_position)


def _set_position(transfer: FileTransfer, handle: int):
    async def set_position(file_handle: int, position: int) -> list[ua.Variant]:
        f = transfer.opened(handle, file_handle)
        f.position = min(position, len(f.data))
        return []
    return spec_method([ua.VariantType.UInt32, ua.VariantType.UInt64], set_position)


def _open(transfer: FileTransfer, handle: int):
    async def open_again(mode: int) -> list[ua.Variant]:
        raise CallRefused(ua.StatusCodes.BadInvalidState, "the file is open for reading under the handle "
                          "GenerateFileForRead returned")
    return spec_method([ua.VariantType.Byte], open_again)


def _write(transfer: FileTransfer, handle: int):
    async def write(file_handle: int, data: bytes) -> list[ua.Variant]:
        raise CallRefused(ua.StatusCodes.BadNotWritable, "a result file is read only")
    return spec_method([ua.VariantType.UInt32, ua.VariantType.ByteString], write)


_FILE_METHODS = {"Read": _read, "Close": _close, "GetPosition": _get_position, "SetPosition": _set_position,
                 "Open": _open, "Write": _write}

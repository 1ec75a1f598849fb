"""The OPC UA server beside the REST API: the same service facade behind both, one owner of jobs and of the cell
(docs/opcua.md).

:class:`OpcuaGateway` is made with the REST app and follows its lifespan: :meth:`~OpcuaGateway.prepare` builds
the address space before the daemon starts (asyncua's standard address space takes seconds of CPU on the loop,
which must not happen while the 50 Hz safety loop runs) and writes it as NodeSet2 XML (:attr:`nodeset_file`);
:meth:`~OpcuaGateway.start` listens and starts the feed once it has started, :meth:`~OpcuaGateway.stop` closes
both before the daemon closes.
"""

from __future__ import annotations

import asyncio
import logging
from datetime import UTC, datetime
from pathlib import Path

from asyncua import Server, ua
from tandemscan.config.models import OpcuaConfig
from tandemscan.daemon.api.facade import ServiceFacade
from tandemscan.daemon.api.guard import BindRefused, check_bind
from tandemscan.daemon.api.models import JobRequest
from tandemscan.daemon.api.opcua.calls import CallRefused, spec_method, text_method
from tandemscan.daemon.api.opcua.feed import CellFeed, device_names
from tandemscan.daemon.api.opcua.model import CONTROL_METHODS, NAMESPACE_URI, SAFETY_METHODS, CellNodes, build_model
from tandemscan.daemon.api.opcua.results import FileTransfer, ResultCatalog
from tandemscan.daemon.api.opcua.security import (
    APPLICATION_URI,
    PlantUserManager,
    RoleRuleset,
    TrustList,
    ensure_server_identity,
    load_users,
)
from tandemscan.daemon.jobs.manager import JobRequestError
from tandemscan.drivers.tasks import cancel_and_wait

log = logging.getLogger(__name__)
VT = ua.VariantType
STR = VT.String
NODESET_FILE = "tandemscan-cell.NodeSet2.xml"


def _text(value: str) -> ua.Variant:
    return ua.Variant(value, STR)


def gateway_for(facade: ServiceFacade) -> OpcuaGateway | None:
    """The OPC UA server of the facade's daemon where ``[opcua] enabled``; bound to ``[opcua] host``, else the
    REST host. Refused (:class:`~tandemscan.daemon.api.guard.BindRefused`) beyond loopback while anonymous access is
    allowed."""
    daemon = facade.daemon
    config = daemon.config.opcua
    if not config.enabled:
        return None
    host = config.host or daemon.config.daemon.host
    if config.allow_anonymous:
        try:
            check_bind(host, None)
        except BindRefused as e:
            raise BindRefused(f"refusing to serve OPC UA on {host} with anonymous access: set [opcua] "
                              "allow_anonymous = false, or bind to 127.0.0.1") from e
    return OpcuaGateway(facade, config, daemon.state_dir, host)


def _revise_publishing_intervals(server: Server, floor_ms: float) -> None:
    """Make ``server`` revise every subscription's publishing interval up to ``floor_ms`` (ms), as OPC 10000-4
    5.13.2 lets a server revise a requested interval to the fastest it supports (asyncua grants any interval).
    Each subscription wakes the event loop once an interval: twenty clients asking for 50 ms would be 400 wake-ups
    a second beside the 50 Hz safety loop, for values that change a few times a second."""
    service = server.iserver.subscription_service
    create = service.create_subscription

    async def create_revised(params: ua.CreateSubscriptionParameters, *args, **kwargs):
        params.RequestedPublishingInterval = max(float(params.RequestedPublishingInterval), floor_ms)
        return await create(params, *args, **kwargs)

    service.create_subscription = create_revised


class OpcuaGateway:
    """The OPC UA server over ``facade``, bound to ``host`` and ``config.port``; its certificate, key, trust list
    and rejected certificates in ``state_dir / "opcua"``."""

    def __init__(self, facade: ServiceFacade, config: OpcuaConfig, state_dir: Path, host: str):
        self.facade, self.config, self.host = facade, config, host
        self.folder = Path(state_dir) / "opcua"
        self.server: Server | None = None
        self.nodes: CellNodes | None = None
        self.results = ResultCatalog(facade, simulated=facade.daemon.cell.simulation is not None)
        self.transfer: FileTransfer | None = None
        self._feed_task: asyncio.Task | None = None
        self._events: set[asyncio.Task] = set()

    @property
    def endpoint(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.config.port}/tandemscan/"

    async def prepare(self) -> None:
        """The server set up with its address space, security and methods; not listening yet."""
        cfg = self.config
        identity = await asyncio.to_thread(ensure_server_identity, self.folder / "own")
        users = await asyncio.to_thread(load_users, cfg)
        trust = TrustList(cfg.trust_dir or self.folder / "trusted", self.folder / "rejected")
        server = Server(user_manager=PlantUserManager(users, cfg.allow_anonymous))
        await server.init()
        _revise_publishing_intervals(server, cfg.min_publishing_interval_ms)
        server.set_endpoint(self.endpoint)
        server.set_server_name("tandemscan cell")
        await server.set_application_uri(APPLICATION_URI)
        server.product_uri = "urn:tandemscan"
        server.manufacturer_name = cfg.manufacturer
        await server.load_certificate(str(identity.certificate))
        await server.load_private_key(str(identity.private_key))
        server.set_security_policy([getattr(ua.SecurityPolicyType, p) for p in cfg.security_policies],
                                   permission_ruleset=RoleRuleset())
        tokens = [ua.UserNameIdentityToken] + ([ua.AnonymousIdentityToken] if cfg.allow_anonymous else [])
        server.set_identity_tokens(tokens)
        server.allow_remote_admin(False)
        server.set_certificate_validator(trust)
        await server.set_build_info(APPLICATION_URI, cfg.manufacturer, "tandemscan", self.facade.version,
                                    self.facade.version, datetime.now(UTC))
        identification = {"Manufacturer": cfg.manufacturer, "Model": cfg.model, "SerialNumber": cfg.serial_number,
                          "SoftwareRevision": self.facade.version,
                          "ProductInstanceUri": f"{APPLICATION_URI}:{cfg.serial_number}"}
        self.nodes = await build_model(server, identification, list(device_names(self.facade)))
        await server.load_data_type_definitions()
        self.transfer = FileTransfer(server, self.nodes)
        self.server = server
        self._link_methods()
        # ResultReady from ResultManagement (OPC 40001-101) and from the Server object, where plant clients listen
        self._result_ready = [await server.get_event_generator(self.nodes.result_ready_type, source)
                              for source in (self.nodes.result_management, server.nodes.server)]
        for generator in self._result_ready:
            generator.event.data_types["Result"] = VT.ExtensionObject  # the type's field has no default value
        await server.export_xml_by_ns(str(self.nodeset_file), [NAMESPACE_URI], export_values=True)

    @property
    def nodeset_file(self) -> Path:
        """The NodeSet2 XML of this server's own namespace, written at each start for clients to import."""
        return self.folder / NODESET_FILE

    async def start(self) -> None:
        """Listen, and follow the daemon's events."""
        await self.server.start()
        feed = CellFeed(self.server, self.nodes, self.facade, self._on_completed)
        self._feed_task = asyncio.create_task(feed.run(), name="opcua-feed")
        log.info("OPC UA server on %s (%s)", self.endpoint, ", ".join(self.config.security_policies))

    async def stop(self) -> None:
        await cancel_and_wait(self._feed_task, *self._events)
        if self.server is not None:
            await self.transfer.close_all()
            await self.server.stop()
            # a session whose client went away keeps its subscriptions for the session timeout (OPC 10000-4
            # 6.7); asyncua's stop leaves them, and has no public list of sessions
            for session in list(self.server.iserver._external_sessions.values()):
                await session.close_session(True)

    # ------------------------------------------------------------ methods

    def _link(self, path: str, callback) -> None:
        self.server.link_method(self.server.get_node(self.nodes.nodeid(path)), callback)

    def _link_methods(self) -> None:
        actions = {"StartJob": self._start_job, "PauseJob": self._job_action("pause"),
                   "ResumeJob": self._job_action("resume"), "CancelJob": self._job_action("cancel"),
                   "StopAllMotion": self._stop_all_motion, "ResetLatch": self._reset_latch}
        for name, spec in CONTROL_METHODS.items():
            self._link(f"Production.{name}", text_method([STR] * len(spec.inputs), len(spec.outputs), actions[name]))
        for name, spec in SAFETY_METHODS.items():
            self._link(f"Monitoring.Safety.{name}", text_method([], len(spec.outputs), actions[name]))
        rm = "ResultManagement"
        self._link(f"{rm}.GetLatestResult", spec_method([VT.Int32], self._get_latest_result))
        self._link(f"{rm}.GetResultById", spec_method([STR, VT.Int32], self._get_result_by_id))
        self._link(f"{rm}.GetResultIdListFiltered",
                   spec_method([VT.ExtensionObject, VT.ExtensionObject, VT.UInt32, VT.Int32], self._result_ids))
        self._link(f"{rm}.ReleaseResultHandle", spec_method([VT.UInt32], self._release_result_handle))
        self._link(f"{rm}.ResultTransfer.GenerateFileForRead", spec_method([VT.ExtensionObject], self._generate))

    async def _start_job(self, plan: str, part_number: str, serial_number: str) -> list[ua.Variant]:
        req = JobRequest(plan=plan or None, part_number=part_number or None, serial_number=serial_number or None)
        job, _ = await self.facade.submit(req, None)
        return [_text(job.id), _text(f"job {job.id} queued: plan {job.plan}, {job.steps_total} steps")]

    def _job_action(self, verb: str):
        async def act(job_id: str) -> list[ua.Variant]:
            if not job_id:
                raise CallRefused(ua.StatusCodes.BadInvalidArgument, "JobId is empty")
            job = await self.facade.act(job_id, verb)
            return [_text(f"job {job.id} is {job.state}")]
        return act

    async def _stop_all_motion(self) -> list[ua.Variant]:
        await self.facade.safety_stop("OPC UA")
        return [_text("safety stop latched: all motion halted")]

    async def _reset_latch(self) -> list[ua.Variant]:
        await self.facade.safety_reset()
        return [_text("safety latch cleared")]

    async def _get_latest_result(self, timeout_ms: int) -> list[ua.Variant]:
        return self._result_outputs(await self.results.latest())

    async def _get_result_by_id(self, result_id: str, timeout_ms: int) -> list[ua.Variant]:
        return self._result_outputs(await self.results.result(result_id))

    @staticmethod
    def _result_outputs(result) -> list[ua.Variant]:
        return [ua.Variant(0, VT.UInt32), ua.Variant(result, VT.ExtensionObject), ua.Variant(0, VT.Int32)]

    async def _result_ids(self, content_filter, ordered_by, max_results: int, timeout_ms: int) -> list[ua.Variant]:
        if not isinstance(content_filter, ua.ContentFilter) or content_filter.Elements:
            raise CallRefused(ua.StatusCodes.BadFilterNotAllowed, "only an empty ContentFilter is supported")
        ids = await self.results.ids(max_results)
        return [ua.Variant(0, VT.UInt32), ua.Variant(ids, STR), ua.Variant(0, VT.Int32)]

    async def _release_result_handle(self, handle: int) -> list[ua.Variant]:
        return [ua.Variant(0, VT.Int32)]

    async def _generate(self, options) -> list[ua.Variant]:
        result_id = getattr(options, "ResultId", None)
        if not isinstance(result_id, str) or not result_id:
            raise CallRefused(ua.StatusCodes.BadInvalidArgument, "GenerateOptions must be a "
                              "ResultTransferOptionsDataType with a ResultId")
        f = await self.transfer.generate_for_read(await self.results.file(result_id))
        return [ua.Variant(f.node.nodeid, VT.NodeId), ua.Variant(f.handle, VT.UInt32),
                ua.Variant(ua.NodeId(), VT.NodeId)]

    # ------------------------------------------------------------ events

    def _on_completed(self, job_id: str) -> None:
        task = asyncio.get_running_loop().create_task(self._announce(job_id), name=f"opcua-result-{job_id}")
        self._events.add(task)
        task.add_done_callback(self._events.discard)

    async def _announce(self, job_id: str) -> None:
        """Emit ``ResultReady`` for a job that completed."""
        try:
            result = await self.results.result(job_id)
        except (CallRefused, JobRequestError) as e:
            log.warning("no ResultReady for job %s: %s", job_id, e)
            return
        for generator in self._result_ready:
            generator.event.Result = result
            generator.event.Severity = 100
            await generator.trigger(message=f"result {job_id} ready")

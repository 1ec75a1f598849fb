"""The OPC UA server beside REST (docs/opcua.md) over a daemon on the simulated cell: asyncua clients over a
secure channel (Basic256Sha256, SignAndEncrypt) with user names and passwords, and node-opcua's client as an
independent stack. Certificates are made once per module; each test starts its own daemon (REST on uvicorn, OPC
UA on a free port, both on 127.0.0.1)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shutil
import stat
from pathlib import Path

import httpx
import pytest
from asyncua import ua
from opcua_clients import make_client_identity, secure_client
from serving import running_server
from tandemscan.config import load_config
from tandemscan.config.models import OpcuaUserConfig
from tandemscan.daemon.api.app import create_app
from tandemscan.daemon.api.guard import BindRefused
from tandemscan.daemon.api.opcua.model import NAMESPACE_URI
from tandemscan.daemon.api.opcua.security import hash_password, verify_password
from tandemscan.daemon.service import Daemon
from tandemscan.pipeline.planning.plan import Plan, Scan
from tandemscan.sim_drivers.hil_box import free_port

NODE_DIR = Path(__file__).resolve().parents[1] / "node"
CHEAP = (2**4, 8, 1)  # scrypt cost of the test users' hashes: the login path is the same, only faster
USERS = {"operator": OpcuaUserConfig(role="operator", password_hash=hash_password("op-pw", CHEAP)),
         "viewer": OpcuaUserConfig(role="viewer", password_hash=hash_password("view-pw", CHEAP))}


@pytest.fixture(scope="module")
def identities(tmp_path_factory):
    folder = tmp_path_factory.mktemp("opcua-clients")
    return {"trusted": make_client_identity(folder, "trusted"), "untrusted": make_client_identity(folder, "stranger")}


class Cell:
    """A running daemon: REST ``http``, OPC UA ``url``, the server's certificate and the daemon."""

    def __init__(self, http: httpx.AsyncClient, url: str, server_cert: Path, daemon: Daemon, ns_uri: str):
        self.http, self.url, self.server_cert, self.daemon, self.ns_uri = http, url, server_cert, daemon, ns_uri

    def client(self, identity, user: str | None = "operator", password: str | None = "op-pw", load_types=True):
        return secure_client(self.url, identity, self.server_cert, user, password, load_types=load_types)


@pytest.fixture
async def cell(tmp_path, identities):
    state = tmp_path / "state"
    (state / "plans").mkdir(parents=True)
    Plan(name="short", steps=[Scan()]).save(state / "plans" / "short.toml")
    (state / "opcua" / "trusted").mkdir(parents=True)
    shutil.copy(identities["trusted"].certificate, state / "opcua" / "trusted" / "trusted.der")
    config = load_config()
    port = free_port()
    config = config.model_copy(update={"opcua": config.opcua.model_copy(
        update={"enabled": True, "port": port, "users": USERS})})
    daemon = Daemon(config, state)
    async with running_server(create_app(daemon, manage_lifecycle=True)) as rest:
        async with httpx.AsyncClient(base_url=rest, timeout=30) as http:
            yield Cell(http, f"opc.tcp://127.0.0.1:{port}/tandemscan/", state / "opcua" / "own" / "server.der",
                       daemon, NAMESPACE_URI)


def node(client, ns: int, path: str):
    return client.get_node(ua.NodeId(path, ns))


async def raw_call(client, ns: int, obj: str, method: str, *args: ua.Variant) -> ua.CallMethodResult:
    """The call's result as it comes (status, outputs), without asyncua raising on a Bad status."""
    req = ua.CallMethodRequest(ObjectId=ua.NodeId(obj, ns), MethodId=ua.NodeId(method, ns), InputArguments=list(args))
    return (await client.uaclient.call([req]))[0]


class Changes:
    """Data changes and events a subscription delivers (asyncua's handler)."""

    def __init__(self):
        self.values: dict[str, list] = {}
        self.events: list = []
        self.names: dict = {}
        self.changed = asyncio.Event()

    def datachange_notification(self, n, val, data):
        self.values.setdefault(self.names[n.nodeid], []).append(val)
        self.changed.set()

    def event_notification(self, event):
        self.events.append(event)
        self.changed.set()

    async def wait_for(self, predicate, timeout_s: float = 120.0):
        async with asyncio.timeout(timeout_s):
            while not predicate():
                self.changed.clear()
                await self.changed.wait()


async def subscribe(client, ns: int, paths: list[str], handler: Changes, events: bool = False):
    sub = await client.create_subscription(50, handler)
    nodes = [node(client, ns, p) for p in paths]
    handler.names.update({n.nodeid: p for n, p in zip(nodes, paths, strict=True)})
    await sub.subscribe_data_change(nodes)
    if events:
        ev_type = await client.nodes.root.get_child(["0:Types", "0:EventTypes", "0:BaseEventType",
                                                     f"{ns}:ResultReadyEventType"])
        await sub.subscribe_events(node(client, ns, "ResultManagement"), ev_type)
        await sub.subscribe_events(client.nodes.server, ev_type)
    return sub


async def read_result_file(client, ns: int, result_id: str) -> bytes:
    """The result file through GenerateFileForRead, Read in chunks and Close (OPC 40001-101)."""
    transfer = node(client, ns, "ResultManagement.ResultTransfer")
    file_id, handle, _ = await transfer.call_method(ua.NodeId("ResultManagement.ResultTransfer.GenerateFileForRead",
                                                              ns), ua.ResultTransferOptionsDataType(ResultId=result_id))
    f = client.get_node(file_id)
    read, close = await f.get_child(["0:Read"]), await f.get_child(["0:Close"])
    data = b""
    while chunk := await f.call_method(read, ua.Variant(handle, ua.VariantType.UInt32),
                                       ua.Variant(1000, ua.VariantType.Int32)):
        data += chunk
    await f.call_method(close, ua.Variant(handle, ua.VariantType.UInt32))
    return data


@pytest.mark.slow
async def test_secure_client_runs_a_job_and_fetches_its_result(cell, identities):
    async with cell.client(identities["trusted"]) as client:
        ns = await client.get_namespace_index(cell.ns_uri)
        names = {(await n.read_browse_name()).Name for n in await node(client, ns, "Cell").get_children()}
        assert names == {"Identification", "Monitoring", "Production", "ResultManagement"}
        children = await node(client, ns, "Monitoring.Devices").get_children()
        devices = {(await n.read_browse_name()).Name for n in children}
        assert devices == {d["name"] for d in cell.daemon.supervisor.snapshot()["devices"]}
        assert await node(client, ns, "Identification.SoftwareRevision").read_value() == cell.daemon.version
        assert await node(client, ns, "Monitoring.AllConnected").read_value() is True

        changes = Changes()
        sub = await subscribe(client, ns, ["Production.ActiveJob.Progress", "Production.ActiveJob.State",
                                           "Monitoring.Safety.Latched"], changes, events=True)
        # asked for 50 ms, revised up to the server's fastest ([opcua] min_publishing_interval_ms)
        assert sub.parameters.RequestedPublishingInterval == cell.daemon.config.opcua.min_publishing_interval_ms
        # the latch: stop all motion, then reset it (both through OPC UA, seen as data changes)
        await node(client, ns, "Monitoring.Safety").call_method(ua.NodeId("Monitoring.Safety.StopAllMotion", ns))
        await changes.wait_for(lambda: True in changes.values.get("Monitoring.Safety.Latched", []))
        assert "operator stop (OPC UA)" in (await cell.http.get("/v1/devices")).json()["safety"]["reason"]
        await node(client, ns, "Monitoring.Safety").call_method(ua.NodeId("Monitoring.Safety.ResetLatch", ns))
        await changes.wait_for(lambda: changes.values["Monitoring.Safety.Latched"][-1] is False)

        job_id, message = await node(client, ns, "Production").call_method(
            ua.NodeId("Production.StartJob", ns), "short", "PN-4711", "SN-0042")
        assert "queued" in message
        rest_job = (await cell.http.get(f"/v1/jobs/{job_id}")).json()
        assert (rest_job["plan"], rest_job["part_number"], rest_job["serial_number"]) == ("short", "PN-4711", "SN-0042")
        await changes.wait_for(lambda: len(changes.events) == 2, timeout_s=240)  # from ResultManagement and Server
        assert {e.SourceNode for e in changes.events} == {node(client, ns, "ResultManagement").nodeid,
                                                          client.nodes.server.nodeid}
        result = changes.events[0].Result.ResultMetaData
        assert (result.ResultId, result.JobId) == (job_id, job_id)
        assert (result.ProductId, result.PartId) == ("PN-4711", "SN-0042")
        assert result.InternalRecipeId == "short" and result.IsSimulated and result.FileFormat == "JSON"
        assert 100.0 in changes.values["Production.ActiveJob.Progress"]
        assert changes.values["Production.ActiveJob.State"][-1] == "succeeded"

        _, latest, error = await node(client, ns, "ResultManagement").call_method(
            ua.NodeId("ResultManagement.GetLatestResult", ns), ua.Variant(0, ua.VariantType.Int32))
        assert error == 0 and latest.ResultMetaData.ResultId == job_id
        data = await read_result_file(client, ns, job_id)
        rest = await cell.http.get(f"/v1/jobs/{job_id}/report")
        assert rest.status_code == 200 and data == rest.content  # byte for byte

        # a refusal: the REST rule (only a running job pauses) as a status code with its text
        res = await raw_call(client, ns, "Production", "Production.PauseJob", ua.Variant(job_id))
        http = await cell.http.post(f"/v1/jobs/{job_id}/pause")
        assert res.StatusCode.value == ua.StatusCodes.BadInvalidState and http.status_code == 409
        assert res.OutputArguments[-1].Value == http.json()["detail"]
        res = await raw_call(client, ns, "ResultManagement", "ResultManagement.GetResultById",
                             ua.Variant("nope"), ua.Variant(0, ua.VariantType.Int32))
        assert res.StatusCode.value == ua.StatusCodes.BadNotFound


@pytest.mark.slow
async def test_viewer_may_not_call_and_strangers_are_refused(cell, identities, caplog):
    async with cell.client(identities["trusted"], "viewer", "view-pw") as client:
        ns = await client.get_namespace_index(cell.ns_uri)
        assert await node(client, ns, "Monitoring.Safety.Latched").read_value() is False
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            await node(client, ns, "Monitoring.Safety").call_method(ua.NodeId("Monitoring.Safety.StopAllMotion", ns))
    assert not cell.daemon.supervisor.snapshot()["safety"]["latched"]
    refused = (ua.UaError, OSError)  # the refusal's status, or the connection the server closed after it
    with pytest.raises(refused):  # a certificate that is not in the trust list
        async with cell.client(identities["untrusted"]):
            pass
    assert list((cell.server_cert.parent.parent / "rejected").glob("*.der"))
    caplog.set_level(logging.WARNING, logger="tandemscan")
    for user, password in (("operator", "wrong"), ("nobody", "op-pw"), (None, None)):  # None: anonymous
        with pytest.raises(refused):
            async with cell.client(identities["trusted"], user, password):
                pass
    refusals = [r.getMessage() for r in caplog.records if "OPC UA login refused" in r.getMessage()]
    assert refusals == ["OPC UA login refused: wrong password for 'operator'",
                        "OPC UA login refused: unknown user 'nobody'"]
    key = cell.server_cert.parent / "server.pem"
    assert stat.S_IMODE(os.stat(key).st_mode) == 0o600


def test_passwords_hash_and_verify():
    stored = hash_password("s3cret", CHEAP)
    assert stored.startswith("scrypt$") and stored != hash_password("s3cret", CHEAP)  # salted
    assert verify_password("s3cret", stored) and not verify_password("s3cret!", stored)
    assert not verify_password("s3cret", "not-a-hash")


def test_anonymous_access_binds_to_loopback_only(sim_config, tmp_path):
    config = sim_config.model_copy(update={"opcua": sim_config.opcua.model_copy(
        update={"enabled": True, "allow_anonymous": True, "host": "0.0.0.0"})})
    with pytest.raises(BindRefused, match="anonymous"):
        create_app(Daemon(config, tmp_path / "state"), manage_lifecycle=True)


@pytest.mark.slow
async def test_node_opcua_client_browses_subscribes_and_calls(cell, identities, tmp_path):
    """node-opcua, an independent stack (tests/node/client.mjs), gets what asyncua and REST get."""
    args = ["node", str(NODE_DIR / "client.mjs"), cell.url, str(identities["trusted"].certificate),
            str(identities["trusted"].private_key), str(tmp_path / "pki"), "operator", "op-pw"]
    proc = await asyncio.create_subprocess_exec(*args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    stdout, stderr = await asyncio.wait_for(proc.communicate(), 120)
    assert proc.returncode == 0, stderr.decode()[-2000:]
    lines = [line for line in stdout.decode().splitlines() if line.startswith("{")]  # node-opcua logs to stdout too
    assert lines, stderr.decode()[-2000:]
    out = json.loads(lines[-1])
    assert out["cell"] == ["Identification", "Monitoring", "Production", "ResultManagement"]
    assert out["devices"] == sorted(d["name"] for d in cell.daemon.supervisor.snapshot()["devices"])
    assert out["manufacturer"] == cell.daemon.config.opcua.manufacturer
    assert out["stop"]["status"] == "Good" and out["reset"]["status"] == "Good"
    assert out["latched"][:3] == [False, True, False]  # the subscription saw the latch set and cleared
    http = await cell.http.post("/v1/jobs", json={"plan": "no-such-plan"})
    assert out["unknown_plan"]["status"] == "BadNotFound" and http.status_code == 404
    assert out["unknown_plan"]["outputs"][-1] == http.json()["detail"]


def malformed_calls(ns: int, job_id: str) -> list[ua.CallMethodRequest]:
    """Calls no well-behaved client makes: arguments missing, too many, of the wrong type or size, unknown nodes,
    file handles never opened, filters not supported."""
    s, i32, u32 = ua.VariantType.String, ua.VariantType.Int32, ua.VariantType.UInt32
    shapes = [
        ("Production", "Production.StartJob", []),
        ("Production", "Production.StartJob", [ua.Variant(1, i32)] * 3),
        ("Production", "Production.StartJob", [ua.Variant("x" * 5000, s), ua.Variant("", s), ua.Variant("", s)]),
        ("Production", "Production.PauseJob", [ua.Variant(job_id, s), ua.Variant(job_id, s)]),
        ("Production", "Production.CancelJob", [ua.Variant(["a", "b"], s)]),
        ("Production", "Production.NoSuchMethod", []),
        ("NoSuchObject", "Production.StartJob", []),
        ("ResultManagement", "ResultManagement.GetResultById", [ua.Variant(3, u32), ua.Variant(0, i32)]),
        ("ResultManagement", "ResultManagement.GetResultIdListFiltered",
         [ua.Variant(ua.ContentFilter(Elements=[ua.ContentFilterElement()])), ua.Variant(ua.ContentFilter()),
          ua.Variant(5, u32), ua.Variant(0, i32)]),
        ("ResultManagement.ResultTransfer", "ResultManagement.ResultTransfer.GenerateFileForRead",
         [ua.Variant(ua.ContentFilter())]),
    ]
    return [ua.CallMethodRequest(ObjectId=ua.NodeId(o, ns), MethodId=ua.NodeId(m, ns), InputArguments=a)
            for o, m, a in shapes * 10]


@pytest.mark.slow
async def test_lost_client_many_subscribers_and_malformed_calls_leave_the_job_alone(cell, identities, caplog):
    caplog.set_level(logging.WARNING)
    trusted = identities["trusted"]
    async with contextlib.AsyncExitStack() as stack:
        clients = [await stack.enter_async_context(cell.client(trusted, "viewer", "view-pw", load_types=False))
                   for _ in range(20)]
        ns = await clients[0].get_namespace_index(cell.ns_uri)
        watchers = [Changes() for _ in clients]
        for client, changes in zip(clients, watchers, strict=True):
            await subscribe(client, ns, ["Production.ActiveJob.State", "Production.ActiveJob.Progress"], changes)
        async with cell.client(trusted) as operator:
            job_id, _ = await node(operator, ns, "Production").call_method(ua.NodeId("Production.StartJob", ns),
                                                                           "short", "", "")
            await watchers[0].wait_for(lambda: "running" in watchers[0].values.get("Production.ActiveJob.State", []))
            async with cell.client(trusted, "viewer", "view-pw", load_types=False) as lost:  # leaves, closing nothing
                await subscribe(lost, ns, ["Production.ActiveJob.Progress", "Monitoring.MovingRobot"], Changes())
                lost.uaclient.protocol.transport.abort()
            results = await operator.uaclient.call(malformed_calls(ns, job_id))
            assert len(results) == 100 and all(r.StatusCode.is_bad() for r in results)
            for changes in watchers:
                await changes.wait_for(lambda c=changes: "succeeded" in c.values.get("Production.ActiveJob.State", []),
                                       timeout_s=240)
                assert 100.0 in changes.values["Production.ActiveJob.Progress"]
            assert (await cell.http.get(f"/v1/jobs/{job_id}")).json()["state"] == "succeeded"
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR
              and r.name.startswith(("tandemscan", "asyncua.server", "uvicorn"))]
    assert not errors, [r.getMessage() for r in errors]


@pytest.mark.slow
async def test_the_nodeset_export_imports_into_another_server(cell):
    """The NodeSet2 XML the server writes at start holds its own namespace: another server imports it whole, with
    the methods' signatures and the result types."""
    from asyncua import Server

    nodeset = cell.server_cert.parent.parent / "tandemscan-cell.NodeSet2.xml"
    other = Server()
    await other.init()
    try:
        await other.import_xml(str(nodeset))
        ns = await other.get_namespace_index(cell.ns_uri)
        children = await other.get_node(ua.NodeId("Monitoring.Devices", ns)).get_children()
        assert {(await c.read_browse_name()).Name for c in children} == \
            {d["name"] for d in cell.daemon.supervisor.snapshot()["devices"]}
        start = other.get_node(ua.NodeId("Production.StartJob", ns))
        inputs = await (await start.get_child(["0:InputArguments"])).read_value()
        assert [a.Name for a in inputs] == ["Plan", "PartNumber", "SerialNumber"]
        meta = other.get_node(ua.NodeId("ResultMetaDataType", ns))
        fields = [f.Name for f in (await meta.read_data_type_definition()).Fields]
        assert fields[:3] == ["ResultId", "HasTransferableDataOnFile", "IsPartial"] and "ResultEvaluation" in fields
        assert (await other.get_node(ua.NodeId("Identification.Manufacturer", ns)).read_value()) == "tandemscan"
    finally:
        await other.stop()


def test_opcua_user_prints_a_config_entry_that_logs_in(monkeypatch, capsys):
    import io
    import tomllib

    from tandemscan.daemon.cli import main

    monkeypatch.setattr("sys.stdin", io.StringIO("s3cret\n"))
    assert main(["opcua-user", "alice", "--role", "operator"]) == 0
    entry = tomllib.loads(capsys.readouterr().out)["opcua"]["users"]["alice"]
    user = OpcuaUserConfig.model_validate(entry)
    assert user.role == "operator" and verify_password("s3cret", user.password_hash)

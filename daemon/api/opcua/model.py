"""The OPC UA address space of the cell: what a client browses, with the browse names of the companion
specifications where they fit (docs/opcua.md, the address space).

One object ``Objects/Cell`` in the namespace :data:`NAMESPACE_URI`, every node with a string NodeId that names
its path (``ns=<ns>;s=Monitoring.Safety.Latched``):

- ``Identification`` (OPC 40001-1 ``MachineIdentification`` / OPC 10000-100 names): ``Manufacturer``, ``Model``,
  ``SerialNumber``, ``SoftwareRevision``, ``ProductInstanceUri``;
- ``Monitoring``: ``MachineryItemState`` (OPC 40001-1's states as text: ``NotAvailable``, ``OutOfService``,
  ``NotExecuting``, ``Executing``), ``AllConnected``, ``MovingRobot``, ``Devices/<device>`` (``Connected``,
  ``State``, ``LastError``, ``Reconnects``) and ``Safety`` (``Latched``, ``Reason``, ``EStop``,
  ``LightCurtainBroken``; methods ``StopAllMotion``, ``ResetLatch``);
- ``Production``: ``ActiveJob`` (``JobId``, ``State``, ``Progress`` %, ``CurrentStep``, ``StepsTotal``,
  ``Plan``, ``PartNumber``, ``SerialNumber``, ``Error``) and the job methods ``StartJob``, ``PauseJob``,
  ``ResumeJob``, ``CancelJob``;
- ``ResultManagement`` (OPC 40001-101): ``GetLatestResult``, ``GetResultById``, ``GetResultIdListFiltered``,
  ``ReleaseResultHandle``, ``Results`` and ``ResultTransfer`` with ``GenerateFileForRead``; it emits
  ``ResultReadyEventType`` events.

The data types are this namespace's own, with the fields and names of OPC 40001-101's (``ResultMetaDataType``,
``ResultDataType``, ``ProcessingTimesDataType``, ``ResultEvaluationEnum``, ``ResultTransferOptionsDataType``): the
companion NodeSets are not loaded into the server.
"""

from __future__ import annotations

from dataclasses import dataclass

from asyncua import Node, Server, ua
from asyncua.common.structures104 import new_enum, new_struct, new_struct_field

NAMESPACE_URI = "urn:tandemscan:ua:cell"
#: OPC 40001-1 MachineryItemState names the ``Monitoring.MachineryItemState`` variable takes
ITEM_STATES = ("NotAvailable", "OutOfService", "NotExecuting", "Executing")
#: the values OPC 40001-101's ``ResultEvaluationEnum`` has
RESULT_EVALUATIONS = ("Undefined", "OK", "NotOK", "NotDecidable")
VT = ua.VariantType


@dataclass
class Method:
    """A method node to create: its browse name, input and output arguments and description."""

    name: str
    inputs: list[ua.Argument]
    outputs: list[ua.Argument]
    description: str


def argument(name: str, datatype: ua.NodeId | int, description: str, array: bool = False) -> ua.Argument:
    """One input or output argument of a method."""
    dt = datatype if isinstance(datatype, ua.NodeId) else ua.NodeId(datatype)
    return ua.Argument(Name=name, DataType=dt, ValueRank=ua.ValueRank.OneDimension if array else ua.ValueRank.Scalar,
                       ArrayDimensions=[0] if array else [], Description=ua.LocalizedText(description))


@dataclass
class CellNodes:
    """The nodes the server writes and links methods to; ``variables`` by path (``"Monitoring.Safety.Latched"``)."""

    ns: int
    cell: Node
    devices: Node
    safety: Node
    production: Node
    result_management: Node
    result_transfer: Node
    result_ready_type: Node
    variables: dict[str, Node]
    types: dict[str, Node]

    def nodeid(self, path: str) -> ua.NodeId:
        return ua.NodeId(path, self.ns)


class ModelBuilder:
    """Adds the cell's nodes to a server that is set up but not started."""

    def __init__(self, server: Server, ns: int):
        self.server, self.ns = server, ns
        self.variables: dict[str, Node] = {}  # by path

    def _id(self, path: str) -> ua.NodeId:
        return ua.NodeId(path, self.ns)

    async def obj(self, parent: Node, path: str, objecttype: int = ua.ObjectIds.BaseObjectType) -> Node:
        return await parent.add_object(self._id(path), ua.QualifiedName(path.rsplit(".", 1)[-1], self.ns),
                                       objecttype=objecttype)

    async def var(self, parent: Node, path: str, value, vt: ua.VariantType, datatype: ua.NodeId | None = None,
                  description: str = "") -> Node:
        node = await parent.add_variable(self._id(path), ua.QualifiedName(path.rsplit(".", 1)[-1], self.ns),
                                         ua.Variant(value, vt), datatype=datatype)
        if description:
            await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.LocalizedText(description)))
        self.variables[path] = node
        return node

    async def method(self, parent: Node, path: str, spec: Method) -> Node:
        node = await parent.add_method(self._id(path), ua.QualifiedName(spec.name, self.ns), None, spec.inputs,
                                       spec.outputs)
        await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.LocalizedText(spec.description)))
        return node

    async def data_types(self) -> dict[str, Node]:
        """OPC 40001-101's result types, in this namespace."""
        s, ns = self.server, self.ns
        evaluation = await new_enum(s, self._id("ResultEvaluationEnum"), ua.QualifiedName("ResultEvaluationEnum", ns),
                                    list(RESULT_EVALUATIONS))
        times, _ = await new_struct(s, self._id("ProcessingTimesDataType"),
                                    ua.QualifiedName("ProcessingTimesDataType", ns), [
                                        new_struct_field("StartTime", VT.DateTime),
                                        new_struct_field("EndTime", VT.DateTime)])
        meta, _ = await new_struct(s, self._id("ResultMetaDataType"), ua.QualifiedName("ResultMetaDataType", ns), [
            new_struct_field("ResultId", VT.String, description="the job id"),
            new_struct_field("HasTransferableDataOnFile", VT.Boolean),
            new_struct_field("IsPartial", VT.Boolean),
            new_struct_field("IsSimulated", VT.Boolean, description="measured on the simulated cell"),
            new_struct_field("ResultState", VT.Int32, description="1: completed"),
            new_struct_field("PartId", VT.String, description="the part's serial number"),
            new_struct_field("ProductId", VT.String, description="the part number"),
            new_struct_field("InternalRecipeId", VT.String, description="the plan"),
            new_struct_field("JobId", VT.String),
            new_struct_field("CreationTime", VT.DateTime, description="when the report was written"),
            new_struct_field("ProcessingTimes", times),
            new_struct_field("ResultUri", VT.String, description="the REST path of the result file"),
            new_struct_field("ResultEvaluation", evaluation, description="the inspection's verdict"),
            new_struct_field("ResultEvaluationDetails", VT.LocalizedText),
            new_struct_field("FileFormat", VT.String, description="QIF or JSON: the result file's format")])
        result, _ = await new_struct(s, self._id("ResultDataType"), ua.QualifiedName("ResultDataType", ns), [
            new_struct_field("ResultMetaData", meta)])
        options, _ = await new_struct(s, self._id("ResultTransferOptionsDataType"),
                                      ua.QualifiedName("ResultTransferOptionsDataType", ns), [
                                          new_struct_field("ResultId", VT.String)])
        return {"ResultEvaluationEnum": evaluation, "ProcessingTimesDataType": times, "ResultMetaDataType": meta,
                "ResultDataType": result, "ResultTransferOptionsDataType": options}


# ---------------------------------------------------------------- the methods' signatures

STRING, UINT32, INT32, NODEID = ua.ObjectIds.String, ua.ObjectIds.UInt32, ua.ObjectIds.Int32, ua.ObjectIds.NodeId
MESSAGE = argument("Message", STRING, "what was done, or why it was refused (the REST problem's detail)")
JOB_ID = argument("JobId", STRING, "the job's id (as in /v1/jobs/{id})")
CONTROL_METHODS = {
    "StartJob": Method("StartJob", [
        argument("Plan", STRING, "a plan name of /v1/plans; empty: the default plan"),
        argument("PartNumber", STRING, "the part number (may be empty)"),
        argument("SerialNumber", STRING, "the part's serial number (may be empty)")],
        [JOB_ID, MESSAGE], "Queue a job (POST /v1/jobs)"),
    "PauseJob": Method("PauseJob", [JOB_ID], [MESSAGE], "Pause a running job at its next step boundary"),
    "ResumeJob": Method("ResumeJob", [JOB_ID], [MESSAGE],
                        "Resume a paused job; after a safety stop this resets the latch, refused while inputs forbid "
                        "motion"),
    "CancelJob": Method("CancelJob", [JOB_ID], [MESSAGE], "Cancel a queued, running or paused job"),
}
SAFETY_METHODS = {
    "StopAllMotion": Method("StopAllMotion", [], [MESSAGE],
                            "Latch an operator safety stop: all motion halts, the running job goes to paused_safety"),
    "ResetLatch": Method("ResetLatch", [], [MESSAGE],
                         "Clear the safety latch; refused while the e-stop or light curtain still forbid motion"),
}


def result_methods(types: dict[str, Node]) -> dict[str, Method]:
    """OPC 40001-101's methods of ``ResultManagement`` with its argument names and types."""
    handle = argument("ResultHandle", UINT32, "0: results are kept; nothing to release")
    result = argument("Result", types["ResultDataType"].nodeid, "the result's metadata")
    error = argument("Error", INT32, "0: no error")
    timeout = argument("Timeout", INT32, "ms; results are answered at once")
    return {
        "GetLatestResult": Method("GetLatestResult", [timeout], [handle, result, error],
                                  "The newest result (of the last job that completed)"),
        "GetResultById": Method("GetResultById", [argument("ResultId", STRING, "the job id"), timeout],
                                [handle, result, error], "The result of one job"),
        "GetResultIdListFiltered": Method("GetResultIdListFiltered", [
            argument("Filter", ua.ObjectIds.ContentFilter, "only an empty filter is supported"),
            argument("OrderedBy", ua.ObjectIds.RelativePath, "ignored: newest first"),
            argument("MaxResults", UINT32, "0: no limit"), timeout],
            [handle, argument("ResultIdList", STRING, "result ids, newest first", array=True), error],
            "Ids of the kept results"),
        "ReleaseResultHandle": Method("ReleaseResultHandle", [handle], [error], "Nothing to release: results are kept"),
    }


def generate_file_method(types: dict[str, Node]) -> Method:
    """``ResultTransfer.GenerateFileForRead`` (OPC 40001-101, the temporary file transfer of OPC 10000-5)."""
    return Method("GenerateFileForRead", [
        argument("GenerateOptions", types["ResultTransferOptionsDataType"].nodeid, "which result")],
        [argument("FileNodeId", NODEID, "a FileType object open for reading"),
         argument("FileHandle", UINT32, "its handle for Read and Close"),
         argument("CompletionStateMachine", NODEID, "null: the file is ready at once")],
        "Open the result's file (results.qif when the job wrote one, else report.json) for reading")


# ---------------------------------------------------------------- building it

async def build_model(server: Server, identification: dict[str, str], device_names: list[str]) -> CellNodes:
    """Add the cell's nodes (every variable at its empty value) to ``server``; methods are linked by the caller."""
    ns = await server.register_namespace(NAMESPACE_URI)
    b = ModelBuilder(server, ns)
    types = await b.data_types()
    objects = server.nodes.objects
    cell = await b.obj(objects, "Cell")

    ident = await b.obj(cell, "Identification")
    for name, value in identification.items():
        await b.var(ident, f"Identification.{name}", value, VT.String)

    monitoring = await b.obj(cell, "Monitoring")
    await b.var(monitoring, "Monitoring.MachineryItemState", "NotAvailable", VT.String,
                description="OPC 40001-1: NotAvailable, OutOfService (a device down or the latch set), "
                            "NotExecuting, Executing (a job running)")
    await b.var(monitoring, "Monitoring.AllConnected", False, VT.Boolean)
    await b.var(monitoring, "Monitoring.MovingRobot", "", VT.String,
                description="measure or tracking while that robot moves; empty at rest (never both)")
    devices = await b.obj(monitoring, "Monitoring.Devices", ua.ObjectIds.FolderType)
    for name in device_names:
        dev = await b.obj(devices, f"Monitoring.Devices.{name}")
        await b.var(dev, f"Monitoring.Devices.{name}.Connected", False, VT.Boolean)
        await b.var(dev, f"Monitoring.Devices.{name}.State", "", VT.String)
        await b.var(dev, f"Monitoring.Devices.{name}.LastError", "", VT.String)
        await b.var(dev, f"Monitoring.Devices.{name}.Reconnects", 0, VT.UInt32)
    safety = await b.obj(monitoring, "Monitoring.Safety")
    await b.var(safety, "Monitoring.Safety.Latched", False, VT.Boolean,
                description="a safety stop is latched: no motion until reset")
    await b.var(safety, "Monitoring.Safety.Reason", "", VT.String)
    await b.var(safety, "Monitoring.Safety.EStop", False, VT.Boolean, description="input: e-stop pressed")
    await b.var(safety, "Monitoring.Safety.LightCurtainBroken", False, VT.Boolean,
                description="input: light curtain broken")
    for name, spec in SAFETY_METHODS.items():
        await b.method(safety, f"Monitoring.Safety.{name}", spec)

    production = await b.obj(cell, "Production")
    job = await b.obj(production, "Production.ActiveJob")
    for name, value, vt, text in (
            ("JobId", "", VT.String, "the job running or paused, else the last one"),
            ("State", "", VT.String, "queued, running, paused, paused_safety, paused_fault, succeeded, "
                                     "succeeded_with_gaps, failed, cancelled"),
            ("Progress", 0.0, VT.Double, "percent"), ("CurrentStep", -1, VT.Int32, "-1: none"),
            ("StepsTotal", 0, VT.Int32, ""), ("Plan", "", VT.String, ""), ("PartNumber", "", VT.String, ""),
            ("SerialNumber", "", VT.String, ""), ("Error", "", VT.String, "why it failed or is paused")):
        await b.var(job, f"Production.ActiveJob.{name}", value, vt, description=text)
    for name, spec in CONTROL_METHODS.items():
        await b.method(production, f"Production.{name}", spec)

    rm = await b.obj(cell, "ResultManagement")
    for name, spec in result_methods(types).items():
        await b.method(rm, f"ResultManagement.{name}", spec)
    await b.obj(rm, "ResultManagement.Results", ua.ObjectIds.FolderType)
    transfer = await b.obj(rm, "ResultManagement.ResultTransfer")
    await b.method(transfer, "ResultManagement.ResultTransfer.GenerateFileForRead",
                   generate_file_method(types))
    ready = await server.nodes.base_event_type.add_object_type(
        b._id("ResultReadyEventType"), ua.QualifiedName("ResultReadyEventType", ns))
    result_field = await ready.add_property(b._id("ResultReadyEventType.Result"), ua.QualifiedName("Result", ns),
                                            ua.Variant(None, VT.Null), datatype=types["ResultDataType"].nodeid)
    await result_field.set_modelling_rule(True)
    return CellNodes(ns, cell, devices, safety, production, rm, transfer, ready, b.variables, types)

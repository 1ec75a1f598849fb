// An independent OPC UA stack against the tandemscan server (tests/daemon/test_opcua.py): node-opcua's client connects
// over Basic256Sha256 SignAndEncrypt with a user name and password, browses the cell, subscribes to the safety
// latch, calls methods and prints one JSON object on a line of its own (node-opcua logs to stdout too).
// Usage: node client.mjs URL CLIENT_CERT CLIENT_KEY PKI_DIR USER PASSWORD
import { OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, TimestampsToReturn, DataType,
         UserTokenType } from "node-opcua-client";
import { OPCUACertificateManager } from "node-opcua-certificate-manager";

const [url, certificateFile, privateKeyFile, pkiDir, userName, password] = process.argv.slice(2);
const NS_URI = "urn:tandemscan:ua:cell";

const certificateManager = new OPCUACertificateManager({ rootFolder: pkiDir, automaticallyAcceptUnknownCertificate: true });
const client = OPCUAClient.create({
  applicationName: "tandemscan-node-test", applicationUri: "urn:tandemscan:test-client",
  securityMode: MessageSecurityMode.SignAndEncrypt, securityPolicy: SecurityPolicy.Basic256Sha256,
  certificateFile, privateKeyFile, clientCertificateManager: certificateManager,
  endpointMustExist: false, connectionStrategy: { maxRetry: 1, initialDelay: 200 },
});
const out = {};
const nodeId = (ns, path) => `ns=${ns};s=${path}`;
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

await client.connect(url);
const session = await client.createSession({ type: UserTokenType.UserName, userName, password });
try {
  const ns = (await session.readNamespaceArray()).indexOf(NS_URI);
  const cell = await session.browse(nodeId(ns, "Cell"));
  out.cell = cell.references.map((r) => r.browseName.name).sort();
  const devices = await session.browse(nodeId(ns, "Monitoring.Devices"));
  out.devices = devices.references.map((r) => r.browseName.name).sort();
  out.manufacturer = (await session.read({ nodeId: nodeId(ns, "Identification.Manufacturer"),
                                           attributeId: AttributeIds.Value })).value.value;

  const sub = await session.createSubscription2({ requestedPublishingInterval: 50, publishingEnabled: true,
                                                  requestedMaxKeepAliveCount: 10, requestedLifetimeCount: 100 });
  const latched = [];
  const item = await sub.monitor({ nodeId: nodeId(ns, "Monitoring.Safety.Latched"), attributeId: AttributeIds.Value },
                                 { samplingInterval: 0, discardOldest: true, queueSize: 10 }, TimestampsToReturn.Both);
  item.on("changed", (dv) => latched.push(dv.value.value));

  const call = async (object, method, args) => {
    const r = await session.call({ objectId: nodeId(ns, object), methodId: nodeId(ns, method),
                                   inputArguments: args.map((value) => ({ dataType: DataType.String, value })) });
    return { status: r.statusCode.name, outputs: (r.outputArguments || []).map((v) => v.value) };
  };
  await sleep(300);
  out.stop = await call("Monitoring.Safety", "Monitoring.Safety.StopAllMotion", []);
  await sleep(500);
  out.reset = await call("Monitoring.Safety", "Monitoring.Safety.ResetLatch", []);
  await sleep(500);
  out.unknown_plan = await call("Production", "Production.StartJob", ["no-such-plan", "", ""]);
  out.latched = latched;
  await sub.terminate();
} finally {
  await session.close();
  await client.disconnect();
}
console.log(JSON.stringify(out));

"""OPC UA subscribers beside ``benchmarks/daemon.py --opcua-subscribers N``: N sessions over Basic256Sha256
SignAndEncrypt, each subscribed (50 ms publishing) to the job's progress, state and current step, the safety latch
and the moving robot, counting the data changes until SIGTERM. Prints ``ready`` once every session subscribed and,
at the end, one JSON object on its last line (docs/opcua.md).

    python benchmarks/opcua_subscribers.py URL CERT KEY SERVER_CERT USER PASSWORD N
"""

from __future__ import annotations

import asyncio
import json
import signal
import sys

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

PATHS = ("Production.ActiveJob.Progress", "Production.ActiveJob.State", "Production.ActiveJob.CurrentStep",
         "Monitoring.Safety.Latched", "Monitoring.MovingRobot")
CLIENT_URI = "urn:tandemscan:bench-client"


class Counter:
    def __init__(self):
        self.changes = 0

    def datachange_notification(self, node, val, data):
        self.changes += 1


async def session(url: str, cert: str, key: str, server_cert: str, user: str, password: str, counter: Counter,
                  stack: list[Client]) -> None:
    client = Client(url, timeout=30)
    client.application_uri = CLIENT_URI
    await client.set_security(SecurityPolicyBasic256Sha256, cert, key, server_certificate=server_cert,
                              mode=ua.MessageSecurityMode.SignAndEncrypt)
    client.set_user(user)
    client.set_password(password)
    await client.connect()
    stack.append(client)
    ns = await client.get_namespace_index("urn:tandemscan:ua:cell")
    sub = await client.create_subscription(50, counter)
    await sub.subscribe_data_change([client.get_node(ua.NodeId(p, ns)) for p in PATHS])


async def main(url, cert, key, server_cert, user, password, n) -> None:
    counter, clients, errors = Counter(), [], 0
    stop = asyncio.Event()
    asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
    for _ in range(int(n)):
        try:
            await session(url, cert, key, server_cert, user, password, counter, clients)
        except (OSError, TimeoutError, ua.UaError):
            errors += 1
    print("ready", flush=True)
    await stop.wait()
    for client in clients:
        try:
            await client.disconnect()
        except (OSError, TimeoutError, ua.UaError):
            errors += 1
    print(json.dumps({"sessions": len(clients), "data_changes": counter.changes, "errors": errors}), flush=True)


if __name__ == "__main__":
    asyncio.run(main(*sys.argv[1:8]))

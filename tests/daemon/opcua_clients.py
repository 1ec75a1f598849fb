"""OPC UA test clients: certificates made once per test session, and asyncua clients over a secure channel
(Basic256Sha256, SignAndEncrypt) with a user name and password (docs/opcua.md)."""

from __future__ import annotations

from contextlib import asynccontextmanager
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from tandemscan.daemon.api.opcua.security import ApplicationIdentity, make_application_identity

CLIENT_URI = "urn:tandemscan:test-client"


def make_client_identity(folder: Path, name: str) -> ApplicationIdentity:
    """A client application certificate and key (application URI :data:`CLIENT_URI`)."""
    return make_application_identity(folder, name, CLIENT_URI, ["localhost"], server=False, days=30)


@asynccontextmanager
async def secure_client(url: str, identity: ApplicationIdentity, server_cert: Path, user: str | None,
                        password: str | None, timeout_s: float = 20.0, load_types: bool = True):
    """A connected asyncua client: SignAndEncrypt, the user's name and password; the namespace's types loaded
    unless not ``load_types``."""
    client = Client(url, timeout=timeout_s)
    client.application_uri = CLIENT_URI
    await client.set_security(SecurityPolicyBasic256Sha256, str(identity.certificate), str(identity.private_key),
                              server_certificate=str(server_cert), mode=ua.MessageSecurityMode.SignAndEncrypt)
    if user is not None:
        client.set_user(user)
        client.set_password(password)
    await client.connect()
    try:
        if load_types:
            await client.load_data_type_definitions()
        yield client
    finally:
        await client.disconnect()

"""OPC UA test clients: certificates made once per test session, and asyncua clients over a secure channel
(Basic256Sha256, SignAndEncrypt) with a user name and password (docs/opcua.md)."""

from __future__ import annotations

from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.cert_gen import dump_private_key_as_pem, generate_private_key, generate_self_signed_app_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

CLIENT_URI = "urn:tandemscan:test-client"


@dataclass(frozen=True)
class ClientIdentity:
    certificate: Path  # DER
    private_key: Path  # PEM


def make_client_identity(folder: Path, name: str) -> ClientIdentity:
    """A client application certificate (RSA 2048, self-signed, application URI :data:`CLIENT_URI`)."""
    folder.mkdir(parents=True, exist_ok=True)
    key = generate_private_key()
    cert = generate_self_signed_app_certificate(
        key, name, {}, [x509.UniformResourceIdentifier(CLIENT_URI), x509.DNSName("localhost")],
        [ExtendedKeyUsageOID.CLIENT_AUTH], days=30)
    identity = ClientIdentity(folder / f"{name}.der", folder / f"{name}.pem")
    identity.certificate.write_bytes(cert.public_bytes(Encoding.DER))
    identity.private_key.write_bytes(dump_private_key_as_pem(key))
    return identity


@asynccontextmanager
async def secure_client(url: str, identity: ClientIdentity, server_cert: Path, user: str | None,
                        password: str | None, timeout_s: float = 20.0):
    """A connected asyncua client: SignAndEncrypt, the user's name and password; the namespace's types loaded."""
    client = Client(url, timeout=timeout_s)
    client.application_uri = CLIENT_URI
    await client.set_security(SecurityPolicyBasic256Sha256, str(identity.certificate), str(identity.private_key),
                              server_certificate=str(server_cert), mode=ua.MessageSecurityMode.SignAndEncrypt)
    if user is not None:
        client.set_user(user)
        client.set_password(password)
    await client.connect()
    try:
        await client.load_data_type_definitions()
        yield client
    finally:
        await client.disconnect()

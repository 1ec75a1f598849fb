"""Who may talk to the OPC UA server: its own certificate, the trust list of client certificates, users and roles.

- The server's certificate and key are made on the first start in ``opcua/own/`` of the state folder (RSA 2048,
  SHA-256, self-signed, ten years; the key file ``0600``) and kept; the application URI in the certificate is
  :data:`APPLICATION_URI`.
- A client's certificate is accepted when it is in the trust list (``[opcua] trust_dir``, default
  ``opcua/trusted/`` in the state folder; DER or PEM files), checked anew whenever the folder changes, so a
  certificate dropped in is trusted without a restart. Rejected ones are written to ``opcua/rejected/`` for an
  administrator to move.
- Users log in with a name and password (the config holds a scrypt hash, :func:`hash_password`); a ``viewer``
  browses, reads and subscribes, an ``operator`` may also call methods (:class:`RoleRuleset`). Anonymous
  sessions are refused unless ``[opcua] allow_anonymous``, and are viewers then.

Password checks run on the event loop (asyncua asks for the user synchronously): a check costs one scrypt
(about 10 ms at the default cost), a success is remembered for the process's life (keyed by an HMAC of the
password with a per-process secret) and failed checks of one user are limited to :data:`FAILED_CHECKS_PER_S`.
See docs/opcua.md.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import hmac
import logging
import os
import secrets
import socket
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

from asyncua import ua
from asyncua.crypto.cert_gen import dump_private_key_as_pem, generate_private_key, generate_self_signed_app_certificate
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID
from tandemscan.config.models import OpcuaConfig, OpcuaUserConfig

log = logging.getLogger(__name__)

#: the server's application URI (in its certificate and its endpoint descriptions)
APPLICATION_URI = "urn:tandemscan:cell"
#: scrypt cost of a new password hash (N, r, p): about 4 MiB and 10 ms
SCRYPT_COST = (2**12, 8, 1)
#: failed password checks of one user name a second before further attempts are refused unchecked
FAILED_CHECKS_PER_S = 5
OPERATOR, VIEWER = "operator", "viewer"


# ---------------------------------------------------------------- passwords

def hash_password(password: str, cost: tuple[int, int, int] = SCRYPT_COST) -> str:
    """``scrypt$N$r$p$salt$hash`` (base64) of ``password``: what ``[opcua.users.NAME] password_hash`` holds."""
    n, r, p = cost
    salt = secrets.token_bytes(16)
    digest = hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, dklen=32)
    b64 = [base64.b64encode(b).decode() for b in (salt, digest)]
    return "$".join(["scrypt", str(n), str(r), str(p), *b64])


def verify_password(password: str, stored: str) -> bool:
    """Whether ``password`` matches a hash of :func:`hash_password` (constant-time compare); False when malformed."""
    try:
        scheme, n, r, p, salt, digest = stored.split("$")
        if scheme != "scrypt":
            return False
        expected = base64.b64decode(digest)
        got = hashlib.scrypt(password.encode(), salt=base64.b64decode(salt), n=int(n), r=int(r), p=int(p),
                             dklen=len(expected))
    except (ValueError, TypeError):
        return False
    return hmac.compare_digest(got, expected)


# ---------------------------------------------------------------- users and roles

@dataclass
class PlantUser(User):
    """An asyncua session user with its tandemscan role (``viewer`` or ``operator``)."""

    plant_role: str = VIEWER


def load_users(config: OpcuaConfig) -> dict[str, OpcuaUserConfig]:
    """The config's users and those of ``users_file`` (``[users.NAME]`` tables; the file wins on a clash)."""
    users = dict(config.users)
    if config.users_file is not None:
        with open(config.users_file, "rb") as f:
            table = tomllib.load(f).get("users", {})
        users.update({name: OpcuaUserConfig.model_validate(u) for name, u in table.items()})
    return users


class PlantUserManager:
    """asyncua's user manager: a user name and password of the config, or an anonymous viewer where allowed."""

    def __init__(self, users: dict[str, OpcuaUserConfig], allow_anonymous: bool):
        self.users = users
        self.allow_anonymous = allow_anonymous
        self._secret = secrets.token_bytes(32)
        self._verified: set[tuple[str, bytes]] = set()
        self._failures: dict[str, list[float]] = {}

    def get_user(self, iserver, username: str | None = None, password: str | None = None,
                 certificate=None) -> User | None:
        """The session's user, or None (the session is refused with BadUserAccessDenied)."""
        if username is None:
            return PlantUser(role=UserRole.User, name="anonymous", plant_role=VIEWER) if self.allow_anonymous else None
        entry = self.users.get(username)
        if entry is None or password is None:
            log.warning("OPC UA login refused: unknown user %r", username)
            return None
        key = (username, hmac.new(self._secret, password.encode(), hashlib.sha256).digest())
        if key not in self._verified:
            if not self._may_check(username) or not verify_password(password, entry.password_hash):
                log.warning("OPC UA login refused: wrong password for %r", username)
                return None
            self._verified.add(key)
        return PlantUser(role=UserRole.User, name=username, plant_role=entry.role)

    def _may_check(self, username: str) -> bool:
        """Count one check of ``username``'s password; False past :data:`FAILED_CHECKS_PER_S` this second."""
        now = time.monotonic()
        recent = [t for t in self._failures.get(username, []) if now - t < 1.0]
        if len(recent) >= FAILED_CHECKS_PER_S:
            return False
        self._failures[username] = [*recent, now]
        return True


_CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
_WRITE = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
_USER_REQUESTS = frozenset(ua.NodeId(t) for t in USER_TYPES)


class RoleRuleset(PermissionRuleset):
    """Which requests a session's user may make: every user's service set, less Call and Write for a viewer."""

    def check_validity(self, user, action_type_id, body) -> bool:
        if action_type_id not in _USER_REQUESTS:
            return False
        if action_type_id in (_CALL, _WRITE):
            return getattr(user, "plant_role", VIEWER) == OPERATOR
        return True


# ---------------------------------------------------------------- certificates

@dataclass(frozen=True)
class ApplicationIdentity:
    """An OPC UA application's certificate (DER) and private key (PEM) files."""

    certificate: Path
    private_key: Path


def make_application_identity(folder: Path, stem: str, uri: str, hostnames: list[str], server: bool,
                              days: int = 3650) -> ApplicationIdentity:
    """A new self-signed application certificate (RSA 2048, SHA-256, application URI ``uri``) and its key
    (``0600``) as ``stem.der`` and ``stem.pem`` in ``folder``; a server's may also act as a client."""
    folder.mkdir(parents=True, exist_ok=True)
    identity = ApplicationIdentity(folder / f"{stem}.der", folder / f"{stem}.pem")
    key = generate_private_key()
    usages = [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH] if server \
        else [ExtendedKeyUsageOID.CLIENT_AUTH]
    cert = generate_self_signed_app_certificate(
        key, stem, {"organizationName": "tandemscan"},
        [x509.UniformResourceIdentifier(uri), *(x509.DNSName(h) for h in hostnames)], usages, days=days)
    fd = os.open(identity.private_key, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(dump_private_key_as_pem(key))
    os.chmod(identity.private_key, 0o600)
    identity.certificate.write_bytes(cert.public_bytes(Encoding.DER))
    return identity


def ensure_server_identity(folder: Path, hostname: str | None = None) -> ApplicationIdentity:
    """The server's certificate and key in ``folder`` (``server.der``, ``server.pem``), made there on the first
    call (valid ten years, key file ``0600``)."""
    identity = ApplicationIdentity(folder / "server.der", folder / "server.pem")
    if identity.certificate.is_file() and identity.private_key.is_file():
        return identity
    identity = make_application_identity(folder, "server", APPLICATION_URI,
                                         [hostname or socket.gethostname(), "localhost"], server=True)
    log.info("OPC UA server certificate made in %s", folder)
    return identity


class TrustList:
    """The certificate validator of client certificates: valid now, with the URI they claim, and in the trust
    list (reloaded when the folder changes); a refused one is kept in ``rejected``."""

    def __init__(self, trusted: Path, rejected: Path):
        self.trusted, self.rejected = trusted, rejected
        trusted.mkdir(parents=True, exist_ok=True)
        self._store = TrustStore([trusted], [])
        self._validator = CertificateValidator(
            CertificateValidatorOptions.TIME_RANGE | CertificateValidatorOptions.URI
            | CertificateValidatorOptions.TRUSTED | CertificateValidatorOptions.PEER_CLIENT, self._store)
        self._loaded_stamp: tuple | None = None

    def _stamp(self) -> tuple:
        return tuple(sorted((p.name, p.stat().st_mtime_ns) for p in self.trusted.iterdir() if p.is_file()))

    async def __call__(self, cert: x509.Certificate, app_description: ua.ApplicationDescription) -> None:
        stamp = await asyncio.to_thread(self._stamp)
        if stamp != self._loaded_stamp:
            await self._store.load()
            self._loaded_stamp = stamp
        try:
            await self._validator.validate(cert, app_description)
        except Exception:
            await asyncio.to_thread(self._keep_rejected, cert)
            log.warning("OPC UA client certificate refused: %s (%s)", cert.subject.rfc4514_string(),
                        app_description.ApplicationUri)
            raise

    def _keep_rejected(self, cert: x509.Certificate) -> None:
        self.rejected.mkdir(parents=True, exist_ok=True)
        name = cert.fingerprint(hashes.SHA1()).hex()  # the thumbprint OPC UA names certificates by
        (self.rejected / f"{name}.der").write_bytes(cert.public_bytes(Encoding.DER))


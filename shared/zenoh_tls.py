"""TLS for the run's Zenoh links: a private CA, the router's certificate, one client certificate per role.

An auth folder (shared/zenoh_auth.py) may hold a `tls/` folder (`nasa auth tls DIR --host H`):

- `ca.pem`: the run's certificate authority, which every side trusts instead of the public ones;
  `ca.key` (0600) is needed only to issue more certificates;
- `router.pem`/`router.key`: the router's, naming the hosts and addresses clients reach it by;
- `<role>.pem`/`<role>.key`: each role's client certificate (common name = the role).

A router listening on a `tls/` endpoint requires a client certificate from the CA (mutual TLS); a
client connecting to a `tls/` endpoint checks the router's certificate against the CA and the
endpoint's host name. The login (users.txt) still says which role a session is: TLS encrypts the
link and keeps out anyone without a certificate. A host needs only ca.pem and its roles' files.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from shared.zenoh_auth import AUTH_ROLES, AuthError

if TYPE_CHECKING:
    import zenoh

TLS_DIR = "tls"
CA = "ca"
ROUTER_CERT = "router"
VALID_DAYS = 3650


def is_tls(endpoints: list[str]) -> bool:
    """Whether any of the endpoints is a TLS one; mixing TLS and plain endpoints is refused."""
    kinds = {e.strip().startswith("tls/") for e in endpoints if e.strip()}
    if len(kinds) > 1:
        raise AuthError(f"endpoints {endpoints} mix tls/ and plain links: use one kind")
    return kinds == {True}


def _write_private(path: Path, data: bytes) -> None:
    tmp = path.with_suffix(".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def _san(host: str):  # noqa: ANN202 (a cryptography GeneralName)
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def init(folder: Path, hosts: list[str], force: bool = False) -> Path:
    """Write `folder`/tls/: a new CA, the router's certificate for `hosts` (plus localhost and
    127.0.0.1) and a client certificate per role. An existing tls/ is kept unless `force`."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    out = folder / TLS_DIR
    if out.exists() and not force:
        raise FileExistsError(f"{out} exists: pass --force to issue every certificate anew")
    names = list(dict.fromkeys([*hosts, "localhost", "127.0.0.1"]))
    for host in names:
        if not host or any(c in host for c in "/: "):
            raise AuthError(f"{host!r} is not a host name or an IP address")
    tmp = folder / (TLS_DIR + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    now = datetime.datetime.now(datetime.UTC)
    pem = serialization.Encoding.PEM

    def key_bytes(key: ec.EllipticCurvePrivateKey) -> bytes:
        return key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())

    Key = ec.EllipticCurvePrivateKey

    def issue(name: str, key: Key, issuer: x509.Name, signer: Key,
              extensions: list[tuple[x509.ExtensionType, bool]]) -> x509.Certificate:
        builder = (x509.CertificateBuilder()
                   .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
                   .issuer_name(issuer).public_key(key.public_key())
                   .serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(minutes=5))
                   .not_valid_after(now + datetime.timedelta(days=VALID_DAYS)))
        for ext, critical in extensions:
            builder = builder.add_extension(ext, critical=critical)
        return builder.sign(signer, hashes.SHA256())

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "nasa-td3 run CA")])
    ca = issue("nasa-td3 run CA", ca_key, ca_name, ca_key, [
        (x509.BasicConstraints(ca=True, path_length=0), True),
        (x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                       key_encipherment=False, data_encipherment=False, key_agreement=False,
                       encipher_only=False, decipher_only=False), True)])
    (tmp / f"{CA}.pem").write_bytes(ca.public_bytes(pem))
    _write_private(tmp / f"{CA}.key", key_bytes(ca_key))
    leaf = x509.BasicConstraints(ca=False, path_length=None)
    # The router's certificate also serves as a client one: a router connects to another site's.
    holders = {ROUTER_CERT: [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]}
    holders |= {role: [ExtendedKeyUsageOID.CLIENT_AUTH] for role in AUTH_ROLES if role != ROUTER_CERT}
    for name, usages in holders.items():
        key = ec.generate_private_key(ec.SECP256R1())
        extensions: list[tuple[x509.ExtensionType, bool]] = [
            (leaf, True), (x509.ExtendedKeyUsage(usages), False)]
        if name == ROUTER_CERT:
            extensions.append((x509.SubjectAlternativeName([_san(h) for h in names]), False))
        cert = issue(name, key, ca_name, ca_key, extensions)
        (tmp / f"{name}.pem").write_bytes(cert.public_bytes(pem))
        _write_private(tmp / f"{name}.key", key_bytes(key))
    (tmp / "hosts.txt").write_text("".join(f"{h}\n" for h in names))
    # The old set is moved aside, not removed, until the new one is in place: a failure between
    # leaves a working set where the services look for it.
    old = folder / (TLS_DIR + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if out.exists():
        os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists():
            os.replace(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)
    return out


def _files(folder: Path, name: str) -> tuple[Path, Path, Path]:
    tls = folder / TLS_DIR
    paths = (tls / f"{CA}.pem", tls / f"{name}.pem", tls / f"{name}.key")
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise AuthError(f"a tls/ endpoint needs the run's certificates, and {', '.join(missing)} "
                        f"is missing: make them with `nasa auth tls {folder} --host ROUTER_HOST`")
    _check(folder, *paths)
    return tuple(p.resolve() for p in paths)  # type: ignore[return-value]


def _check(folder: Path, ca_path: Path, cert_path: Path, key_path: Path) -> None:
    """AuthError unless the certificate is the CA's, in date, and the key is its own: Zenoh would
    refuse such a link only at the handshake, which a client cannot tell from a router not up."""
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives import serialization

    anew = f"`nasa auth tls {folder} --host ROUTER_HOST --force` issues every certificate anew"
    try:
        ca = x509.load_pem_x509_certificate(ca_path.read_bytes())
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as err:  # unreadable, damaged, a passphrase on the key
        raise AuthError(f"cannot read the certificates {ca_path}, {cert_path}, {key_path} "
                        f"({err.__class__.__name__}: {err}): {anew}") from err
    now = datetime.datetime.now(datetime.UTC)
    for path, held in ((ca_path, ca), (cert_path, cert)):
        if not held.not_valid_before_utc <= now <= held.not_valid_after_utc:
            raise AuthError(f"{path} is valid from {held.not_valid_before_utc:%Y-%m-%d %H:%M} to "
                            f"{held.not_valid_after_utc:%Y-%m-%d %H:%M} UTC, not now: {anew}")
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature) as err:
        raise AuthError(f"{cert_path} is not issued by {ca_path} (from another `nasa auth tls`?): "
                        f"{anew}") from err
    if key.public_key() != cert.public_key():
        raise AuthError(f"{key_path} is not the key of {cert_path}: {anew}")


def apply_client(config: zenoh.Config, folder: Path, role: str) -> None:
    """Trust only the run's CA, check the router's name, and present `role`'s certificate."""
    ca, cert, key = _files(folder, role)
    config.insert_json5("transport/link/tls", json.dumps({
        "root_ca_certificate": str(ca), "enable_mtls": True,
        "connect_certificate": str(cert), "connect_private_key": str(key), "verify_name_on_connect": True}))


def apply_router(config: zenoh.Config, folder: Path) -> None:
    """Serve the router's certificate and accept only clients with a certificate from the run's CA."""
    ca, cert, key = _files(folder, ROUTER_CERT)
    config.insert_json5("transport/link/tls", json.dumps({
        "root_ca_certificate": str(ca), "enable_mtls": True,
        "listen_certificate": str(cert), "listen_private_key": str(key),
        "connect_certificate": str(cert), "connect_private_key": str(key), "verify_name_on_connect": True}))

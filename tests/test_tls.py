"""TLS links to a real router on loopback: the run's own CA, mutual certificates, and clear errors."""

from __future__ import annotations

import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from system_harness import REPO

from nasa.up import free_port
from shared import zenoh_auth, zenoh_tls
from shared.zenoh_session import open_client, open_router

RUN = "tlsrun"


@pytest.fixture(scope="module")
def auth_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = zenoh_auth.init(tmp_path_factory.mktemp("tls") / "auth", RUN)
    zenoh_tls.init(folder, ["router.example", "10.1.2.3"])
    return folder


@pytest.fixture
def router(auth_dir: Path):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    with open_router(endpoint, auth=auth_dir):
        yield endpoint


def test_certificates_name_the_router_hosts_and_keys_are_private(auth_dir: Path) -> None:
    tls = auth_dir / zenoh_tls.TLS_DIR
    cert = x509.load_pem_x509_certificate((tls / "router.pem").read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    names = set(san.get_values_for_type(x509.DNSName))
    names |= {str(a) for a in san.get_values_for_type(x509.IPAddress)}
    assert names == {"router.example", "10.1.2.3", "localhost", "127.0.0.1"}
    ca = x509.load_pem_x509_certificate((tls / "ca.pem").read_bytes())
    for role in zenoh_auth.AUTH_ROLES:
        leaf = x509.load_pem_x509_certificate((tls / f"{role}.pem").read_bytes())
        assert leaf.issuer == ca.subject
        leaf.verify_directly_issued_by(ca)  # raises when not signed by the run's CA
        assert stat.S_IMODE((tls / f"{role}.key").stat().st_mode) == 0o600
    assert stat.S_IMODE((tls / "ca.key").stat().st_mode) == 0o600
    with pytest.raises(FileExistsError):
        zenoh_tls.init(auth_dir, ["other"])
    with pytest.raises(zenoh_auth.AuthError):
        zenoh_tls.init(auth_dir.parent / "bad", ["tcp/host:1"])


def test_a_role_with_its_certificate_talks_over_tls(router: str, auth_dir: Path) -> None:
    got: list[bytes] = []
    with open_client(router, timeout_s=10.0, role="learner", auth=auth_dir) as learner, \
            open_client(router, timeout_s=10.0, role="actor", auth=auth_dir) as actor:
        key = f"nasa/{RUN}/learner/weights"
        sub = actor.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
        deadline = time.monotonic() + 10.0
        while not got and time.monotonic() < deadline:
            learner.put(key, b"w")
            time.sleep(0.2)
        sub.undeclare()
    assert got and got[0] == b"w"


def test_a_client_without_the_runs_certificate_is_refused(router: str, auth_dir: Path,
                                                          tmp_path: Path) -> None:
    # Same logins, certificates from another CA: the router does not know that CA.
    other = tmp_path / "other"
    shutil.copytree(auth_dir, other, ignore=shutil.ignore_patterns(zenoh_tls.TLS_DIR))
    zenoh_tls.init(other, [])
    with pytest.raises(zenoh.ZError):
        open_client(router, timeout_s=3.0, role="learner", auth=other)
    # A plain TCP client to the TLS port does not get in either.
    with pytest.raises(zenoh.ZError):
        open_client(router.replace("tls/", "tcp/"), timeout_s=3.0, role="learner", auth=auth_dir)


def test_tls_needs_the_certificates_with_a_clear_error(auth_dir: Path, tmp_path: Path) -> None:
    port = free_port()
    with pytest.raises(zenoh_auth.AuthError, match="auth folder"):
        open_client(f"tls/127.0.0.1:{port}", timeout_s=1.0, role="actor", auth=None)
    bare = zenoh_auth.init(tmp_path / "bare", RUN)  # logins, no tls/
    with pytest.raises(zenoh_auth.AuthError, match="nasa auth tls"):
        open_router(f"tls/127.0.0.1:{port}", auth=bare)
    with pytest.raises(zenoh_auth.AuthError, match="nasa auth tls"):
        open_client(f"tls/127.0.0.1:{port}", timeout_s=1.0, role="actor", auth=bare)
    with pytest.raises(zenoh_auth.AuthError, match="mix"):
        open_client(f"tls/127.0.0.1:{port},tcp/127.0.0.1:{port}", timeout_s=1.0, role="actor", auth=auth_dir)


@pytest.mark.system  # a `nasa` subprocess
def test_nasa_auth_tls_command(tmp_path: Path) -> None:
    folder = tmp_path / "auth"
    run = [sys.executable, "-m", "nasa.cli", "auth"]
    out = subprocess.run([*run, "tls", str(folder), "--host", "lab-router"], cwd=REPO,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "lab-router" in out.stdout and (folder / "tls" / "actor.pem").exists()
    again = subprocess.run([*run, "tls", str(folder)], cwd=REPO, capture_output=True, text=True)
    assert again.returncode == 2 and "--force" in again.stderr
    bad = subprocess.run([*run, "tls", str(tmp_path / "x"), "--host", "a b"], cwd=REPO,
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "not a host name" in bad.stderr


def _reissue(tls: Path, name: str, days: tuple[int, int]) -> None:
    """Re-sign `name`'s certificate by the run's CA, valid from days[0] to days[1] days from now."""
    import datetime

    from cryptography.hazmat.primitives import hashes, serialization

    ca_key = serialization.load_pem_private_key((tls / "ca.key").read_bytes(), None)
    cert = x509.load_pem_x509_certificate((tls / f"{name}.pem").read_bytes())
    now = datetime.datetime.now(datetime.UTC)
    builder = (x509.CertificateBuilder().subject_name(cert.subject).issuer_name(cert.issuer)
               .public_key(cert.public_key()).serial_number(x509.random_serial_number())
               .not_valid_before(now + datetime.timedelta(days=days[0]))
               .not_valid_after(now + datetime.timedelta(days=days[1])))
    for ext in cert.extensions:
        builder = builder.add_extension(ext.value, ext.critical)
    signed = builder.sign(ca_key, hashes.SHA256())  # type: ignore[arg-type]
    (tls / f"{name}.pem").write_bytes(signed.public_bytes(serialization.Encoding.PEM))


@pytest.mark.parametrize("fault", ["expired", "not-yet-valid", "wrong-key", "other-ca", "garbled-key"])
def test_a_certificate_the_handshake_would_refuse_is_named_up_front(tmp_path: Path, fault: str) -> None:
    """Zenoh refuses such a link only at the handshake, which a client reads as "no router" and
    retries forever, and a router as a port it cannot listen on: name the file instead."""
    folder = zenoh_auth.init(tmp_path / "auth", RUN)
    tls = zenoh_tls.init(folder, [])
    for name in ("actor", "router"):
        if fault == "expired":
            _reissue(tls, name, (-10, -1))
        elif fault == "not-yet-valid":
            _reissue(tls, name, (1, 10))
        elif fault == "wrong-key":
            shutil.copy(tls / "learner.key", tls / f"{name}.key")
        elif fault == "garbled-key":
            (tls / f"{name}.key").write_text("-----BEGIN PRIVATE KEY-----\nnot a key\n")
    if fault == "other-ca":
        other = zenoh_tls.init(zenoh_auth.init(tmp_path / "other", RUN), [])
        shutil.copy(other / "ca.pem", tls / "ca.pem")
    port = free_port()
    with pytest.raises(zenoh_auth.AuthError, match="--force"):
        open_client(f"tls/127.0.0.1:{port}", timeout_s=1.0, role="actor", auth=folder)
    with pytest.raises(zenoh_auth.AuthError, match="--force"):
        open_router(f"tls/127.0.0.1:{port}", auth=folder)


def test_reissuing_keeps_the_old_certificates_in_place_until_the_new_ones_are(
    tmp_path: Path, monkeypatch
) -> None:
    tls = zenoh_tls.init(tmp_path, ["lab-router"])
    before = (tls / "actor.pem").read_bytes()
    real_replace = zenoh_tls.os.replace

    def failing_for_the_new_set(src, dst) -> None:  # noqa: ANN001
        if Path(src).name == "tls.tmp":
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(zenoh_tls.os, "replace", failing_for_the_new_set)
    with pytest.raises(OSError, match="No space"):
        zenoh_tls.init(tmp_path, ["lab-router"], force=True)
    monkeypatch.undo()
    assert (tls / "actor.pem").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tls"]
    zenoh_tls.init(tmp_path, ["lab-router"], force=True)
    assert (tls / "actor.pem").read_bytes() != before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tls"]

"""deploy/run/certs.py: the CA and identity certificates (files, permissions, names, extensions, chains), their
refusals, the ``khgrl certs`` command, and a real Zenoh router on loopback with mutual TLS that lets an issued
certificate in and keeps out a client with another CA's certificate or with none."""

from __future__ import annotations

import ipaddress
import json
import stat
import time
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID
from cryptography.x509.verification import PolicyBuilder, Store
from khgrl.common.delivery.transport import free_port
from khgrl.deploy.cli import main as khgrl
from khgrl.deploy.run import certs


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _ext(cert: x509.Certificate, cls):
    return cert.extensions.get_extension_for_class(cls).value


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    """A CA with a router (default hosts), an actor and a learner."""
    d = tmp_path_factory.mktemp("certs") / "pki"
    certs.init_ca(d)
    certs.issue(d, "router")
    certs.issue(d, "actor", "a0")
    certs.issue(d, "learner")
    return d


@pytest.fixture(scope="module")
def other(tmp_path_factory) -> Path:
    """Another CA that issued a certificate with the same name, actor-a0."""
    d = tmp_path_factory.mktemp("certs") / "other"
    certs.init_ca(d)
    certs.issue(d, "actor", "a0")
    return d


# ---- names


def test_common_names_follow_the_convention():
    assert certs.cn_for("actor", "a0") == "actor-a0"
    assert certs.cn_for("human", "scripted") == "human-scripted"
    assert certs.cn_for("learner") == certs.cn_for("learner", "learner") == "learner"
    assert certs.cn_for("actor", "my-robot") == "actor-my-robot"
    assert certs.parse_cn("actor-my-robot") == ("actor", "my-robot")
    assert certs.parse_cn("router") == ("router", "router")


@pytest.mark.parametrize("role, ident, match", [
    ("pilot", "a0", "role 'pilot'"), ("actor", "a/0", "id 'a/0'"), ("actor", "a 0", "id"), ("actor", "*", "id"),
    ("actor", "", "id"), ("actor", "x" * 65, "id"), ("actor", "ä", "printable ASCII"), ("actor", 7, "id"),
])
def test_bad_roles_and_ids_are_refused(pki, role, ident, match):
    with pytest.raises(certs.CertError, match=match):
        certs.cn_for(role, ident)
    with pytest.raises(certs.CertError, match=match):
        certs.issue(pki, role, ident)


# ---- files and extensions


def test_the_ca_is_a_ca_with_a_private_key_in_a_private_directory(pki):
    assert _mode(pki) == 0o700 and _mode(pki / "ca.key") == 0o600
    ca = _cert(pki / "ca.pem")
    assert certs.common_name(pki / "ca.pem").startswith("KhGRL CA ")
    assert _ext(ca, x509.BasicConstraints).ca
    usage = _ext(ca, x509.KeyUsage)
    assert usage.key_cert_sign and usage.crl_sign and not usage.digital_signature
    assert (pki / "ca.key").read_text().startswith("-----BEGIN PRIVATE KEY-----")  # PKCS#8, unencrypted


def test_issued_certificates_have_the_name_key_usage_and_subject_alt_names(pki):
    for cn in ("router", "actor-a0", "learner"):
        cert = _cert(pki / f"{cn}.pem")
        assert _mode(pki / f"{cn}.key") == 0o600
        assert certs.common_name(pki / f"{cn}.pem") == cn
        assert not _ext(cert, x509.BasicConstraints).ca
        assert _ext(cert, x509.KeyUsage).digital_signature
        assert set(_ext(cert, x509.ExtendedKeyUsage)) == {ExtendedKeyUsageOID.SERVER_AUTH,
                                                           ExtendedKeyUsageOID.CLIENT_AUTH}
        assert isinstance(cert.public_key(), ec.EllipticCurvePublicKey) and cert.public_key().curve.name == "secp256r1"
        cert.verify_directly_issued_by(_cert(pki / "ca.pem"))
        assert certs.expires(pki / f"{cn}.pem") <= certs.expires(pki / "ca.pem")
    san = _ext(_cert(pki / "router.pem"), x509.SubjectAlternativeName)
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("127.0.0.1")]
    assert san.get_values_for_type(x509.DNSName) == ["router", "localhost"]
    actor_san = _ext(_cert(pki / "actor-a0.pem"), x509.SubjectAlternativeName)
    assert actor_san.get_values_for_type(x509.DNSName) == ["actor-a0"] and not actor_san.get_values_for_type(
        x509.IPAddress)


def test_chains_verify_as_tls_server_and_client(pki, other):
    """cryptography's verifier (web PKI rules, like rustls-webpki): the router for its names, clients as clients."""
    policy = PolicyBuilder().store(Store([_cert(pki / "ca.pem")]))
    router = _cert(pki / "router.pem")
    for name in (x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))):
        policy.build_server_verifier(name).verify(router, [])
    verified = policy.build_client_verifier().verify(_cert(pki / "actor-a0.pem"), [])
    assert verified.subjects == [x509.DNSName("actor-a0")]
    with pytest.raises(x509.verification.VerificationError):
        policy.build_client_verifier().verify(_cert(other / "actor-a0.pem"), [])
    with pytest.raises(x509.verification.VerificationError):  # a client certificate cannot pass for the router
        policy.build_server_verifier(x509.DNSName("localhost")).verify(_cert(pki / "actor-a0.pem"), [])


def test_router_hosts_become_ip_and_dns_names_and_only_routers_take_them(tmp_path):
    d = tmp_path / "pki"
    certs.init_ca(d, days=30)
    certs.issue(d, "router", hosts=["10.1.2.3", "::1", "gpu-box.lab"], days=400)
    cert = _cert(d / "router.pem")
    san = _ext(cert, x509.SubjectAlternativeName)
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("10.1.2.3"), ipaddress.ip_address("::1")]
    assert san.get_values_for_type(x509.DNSName) == ["router", "gpu-box.lab"]
    assert cert.not_valid_after_utc <= _cert(d / "ca.pem").not_valid_after_utc  # cut to the CA's 30 days
    with pytest.raises(certs.CertError, match="router certificates only"):
        certs.issue(d, "actor", "a0", hosts=["10.1.2.3"])


def test_existing_files_are_kept_unless_forced(tmp_path):
    d = tmp_path / "pki"
    certs.init_ca(d)
    ca_before = (d / "ca.pem").read_bytes()
    with pytest.raises(certs.CertError, match="a CA exists"):
        certs.init_ca(d)
    certs.issue(d, "actor", "a0")
    key_before = (d / "actor-a0.key").read_bytes()
    with pytest.raises(certs.CertError, match="identity actor-a0 exists"):
        certs.issue(d, "actor", "a0")
    assert (d / "ca.pem").read_bytes() == ca_before and (d / "actor-a0.key").read_bytes() == key_before
    certs.issue(d, "actor", "a0", force=True)
    assert (d / "actor-a0.key").read_bytes() != key_before and _mode(d / "actor-a0.key") == 0o600
    certs.init_ca(d, force=True)
    assert (d / "ca.pem").read_bytes() != ca_before
    assert not list(d.glob(".*.tmp"))


def test_issuing_without_a_ca_says_how_to_make_one(tmp_path):
    with pytest.raises(certs.CertError, match="khgrl certs init"):
        certs.issue(tmp_path / "none", "actor", "a0")


def test_identities_are_read_from_the_certificates(tmp_path, other):
    d = tmp_path / "pki"
    certs.init_ca(d)
    certs.issue(d, "router")
    certs.issue(d, "actor", "a-1")
    certs.issue(d, "learner")
    (d / "actor-a-1.pem").rename(d / "robot.pem")  # the file name says nothing; its key stays behind
    (d / "stranger.pem").write_bytes((other / "actor-a0.pem").read_bytes())  # another CA's: not ours
    (d / "notes.pem").write_text("not a certificate")
    found = certs.identities(d)
    assert [(i.role, i.id, i.cn) for i in found] == [("learner", "learner", "learner"), ("actor", "a-1", "actor-a-1"),
                                                      ("router", "router", "router")]
    assert found[1].cert == d / "robot.pem" and found[1].key is None
    assert found[0].key == d / "learner.key"


# ---- khgrl certs


def test_the_command_makes_lists_and_refuses_in_one_line(tmp_path, capsys):
    d = str(tmp_path / "pki")
    assert khgrl(["certs", "init", d, "--days", "100"]) == 0
    assert khgrl(["certs", "issue", d, "--role", "actor", "--id", "a0"]) == 0
    assert khgrl(["certs", "issue", d, "--role", "router", "--host", "10.0.0.5"]) == 0
    capsys.readouterr()
    assert khgrl(["certs", "list", d]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split() == ["ROLE", "ID", "CN", "EXPIRES", "KEY", "NAMES"]
    assert out[1].split()[:3] == ["actor", "a0", "actor-a0"] and "router,10.0.0.5" in out[2]
    for argv, msg in [(["issue", d, "--role", "pilot"], "role 'pilot'"), (["issue", d, "--role", "actor", "--id",
                      "a/0"], "id 'a/0'"), (["issue", d, "--role", "actor", "--id", "a0"], "exists"),
                      (["init", d], "exists"), (["issue", str(tmp_path / "x"), "--role", "actor"], "no CA")]:
        assert khgrl(["certs", *argv]) == 2
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1, err


# ---- real Zenoh with mutual TLS


def _conf(mode: str, tls: dict | None, listen=(), connect=()) -> zenoh.Config:
    """Our settings (scouting off, explicit endpoints); a client tries once and raises if it cannot connect."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if mode == "client":
        conf.insert_json5("connect/timeout_ms", "0")
        conf.insert_json5("connect/exit_on_failure", "true")
    if tls is not None:
        conf.insert_json5("transport/link/tls", json.dumps(tls))
    return conf


@pytest.fixture(scope="module")
def router(pki):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    with zenoh.open(_conf("router", certs.tls_settings(pki, "router", listen=True), listen=[endpoint])) as session:
        yield session, endpoint


def _client(tls: dict | None, endpoint: str) -> zenoh.Session:
    return zenoh.open(_conf("client", tls, connect=[endpoint]))


def test_tls_settings_name_the_files_of_one_side(pki):
    s = certs.tls_settings(pki, "actor-a0", listen=False)
    assert s == {"root_ca_certificate": str((pki / "ca.pem").resolve()), "enable_mtls": True,
                 "connect_certificate": str((pki / "actor-a0.pem").resolve()),
                 "connect_private_key": str((pki / "actor-a0.key").resolve()), "verify_name_on_connect": True}
    assert certs.tls_settings((pki / "ca.pem", pki / "router.pem", pki / "router.key"), listen=True)[
        "listen_private_key"] == str((pki / "router.key").resolve())
    with pytest.raises(certs.CertError, match="expected 'learner'"):
        certs.tls_settings((pki / "ca.pem", pki / "router.pem", pki / "router.key"), "learner", listen=True)
    with pytest.raises(FileNotFoundError, match="monitor-m0.pem"):
        certs.tls_settings(pki, "monitor-m0", listen=False)


def test_issued_certificates_connect_and_the_router_sees_their_names(pki, router):
    session, endpoint = router
    with _client(certs.tls_settings(pki, "actor-a0", listen=False), endpoint) as actor, \
            _client(certs.tls_settings(pki, "learner", listen=False), endpoint) as learner:
        assert sorted(link.auth_identifier for link in session.info.links()) == ["actor-a0", "learner"]
        assert [link.auth_identifier for link in actor.info.links()] == ["router"]
        sub = learner.declare_subscriber("khgrl/test/actor/a0/transitions")
        deadline, got = time.monotonic() + 5.0, None
        while got is None and time.monotonic() < deadline:  # until the subscription has reached the router
            actor.put("khgrl/test/actor/a0/transitions", b"batch")
            time.sleep(0.05)
            got = sub.try_recv()
        assert got is not None and got.payload.to_bytes() == b"batch"


def test_a_certificate_from_another_ca_is_refused_even_with_a_valid_name(pki, other, router):
    _, endpoint = router
    tls = certs.tls_settings((pki / "ca.pem", other / "actor-a0.pem", other / "actor-a0.key"), "actor-a0",
                             listen=False)
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        _client(tls, endpoint)


@pytest.mark.parametrize("tls", [None, "ca_only", "no_enable_mtls"])
def test_a_client_without_a_certificate_is_refused(pki, router, tls):
    """No TLS at all, TLS without a certificate, and a certificate configured without ``enable_mtls`` (Zenoh then
    sends none: the router answers CertificateRequired)."""
    _, endpoint = router
    without = {k: v for k, v in certs.tls_settings(pki, "actor-a0", listen=False).items() if k != "enable_mtls"}
    settings = {None: None, "ca_only": {"root_ca_certificate": str(pki / "ca.pem")}, "no_enable_mtls": without}[tls]
    if tls is None:  # plain TCP to the TLS port
        endpoint = endpoint.replace("tls/", "tcp/")
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        _client(settings, endpoint)


def test_clients_refuse_a_router_without_the_router_certificate(pki, other):
    """Server authentication: a router holding another identity's certificate (no SAN for 127.0.0.1), or one from
    another CA, is refused by a client with an issued certificate."""
    for tls in (certs.tls_settings(pki, "actor-a0", listen=True),
                certs.tls_settings((other / "ca.pem", other / "actor-a0.pem", other / "actor-a0.key"), listen=True)):
        endpoint = f"tls/127.0.0.1:{free_port()}"
        with zenoh.open(_conf("router", tls, listen=[endpoint])):
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                _client(certs.tls_settings(pki, "learner", listen=False), endpoint)

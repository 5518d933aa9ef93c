"""Certificates for mutual TLS between KhGRL processes (``khgrl certs``): a private CA and one key + certificate
per identity, made with the ``cryptography`` library.

Identities: the certificate's common name (CN) is ``<role>-<id>``, or just ``<role>`` when the id is the role
itself (``actor-a0``, ``human-scripted``, ``monitor-m0``, ``learner``, ``launcher``, ``router``); roles are
learner, actor, human, monitor, launcher and router; ids follow the protocol (1-64 characters, no ``/ * $ ? #``
or space; in certificates also printable ASCII). The router's access control matches these names
(``cert_common_names``), so the CN *is* the permission: keep the CA key (``ca.key``) on the machine where
certificates are made, not where they are used.

Files in DIR: ``ca.pem`` + ``ca.key`` (the CA), ``<cn>.pem`` + ``<cn>.key`` per identity. DIR is mode 0700,
keys are mode 0600 and **unencrypted** PKCS#8 PEM (Zenoh reads the key file itself and takes no passphrase):
protect them with file permissions. Keys are ECDSA P-256. Zenoh's TLS is rustls with the *ring* provider: it
takes P-256/P-384 ECDSA, Ed25519 and RSA keys (PKCS#8, SEC1 or PKCS#1 PEM) but not P-521, and mutual TLS is
TLS 1.3 only. Every leaf: not a CA, key usage digitalSignature, extended key usage serverAuth + clientAuth (a
router refuses a client certificate whose EKU lacks clientAuth), and a subjectAltName DNS:<cn>. Only a router's
certificate also carries the hosts clients connect to (``--host``; default IP:127.0.0.1 and DNS:localhost):
clients check that SAN against the host of the endpoint (``verify_name_on_connect``; the CN is never used for
that), so no other identity's certificate can pass for the router.

The same with openssl, for people with their own PKI (any CA works as long as each leaf has the CN, SAN and EKU
below)::

    # the CA (P-256; -nodes: no passphrase)
    openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 825 \\
        -keyout ca.key -out ca.pem -subj "/O=KhGRL/CN=KhGRL CA mylab" \\
        -addext "basicConstraints=critical,CA:TRUE,pathlen:0" -addext "keyUsage=critical,keyCertSign,cRLSign"
    # a leaf: key + request, then signed by the CA with the extensions
    openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes \\
        -keyout actor-a0.key -out actor-a0.csr -subj "/O=KhGRL/CN=actor-a0"
    printf 'basicConstraints=critical,CA:FALSE\\nkeyUsage=critical,digitalSignature\\n%s\\n%s\\n' \\
        'extendedKeyUsage=serverAuth,clientAuth' 'subjectAltName=DNS:actor-a0' > leaf.ext
    openssl x509 -req -in actor-a0.csr -CA ca.pem -CAkey ca.key -CAcreateserial -days 825 \\
        -extfile leaf.ext -out actor-a0.pem
    chmod 600 ca.key actor-a0.key
    # the router: CN router, SAN with every name/address clients use, e.g.
    #   subjectAltName=DNS:router,IP:127.0.0.1,DNS:localhost,IP:192.168.1.10,DNS:gpu-box.lab

One module of ~340 lines on purpose: a sixth of it is the docstring's openssl recipe for people with their own
PKI; the rest makes and reads one directory of certificates (its command line: :mod:`~khgrl.deploy.run.certs_cmd`).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import secrets
from pathlib import Path
from typing import Any, NamedTuple, Sequence

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives import serialization as ser
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from khgrl.common.delivery.acl import ROLES
from khgrl.common.delivery.acl import cn_for as _cn_of
from khgrl.common.wire.checks import ident as _check_id

__all__ = ["ROLES", "CertError", "Identity", "init_ca", "issue", "identities", "common_name", "cn_for",
           "parse_cn", "expires", "tls_settings", "load_cert"]

CA_CERT, CA_KEY = "ca.pem", "ca.key"
DEFAULT_HOSTS = ("127.0.0.1", "localhost")
DEFAULT_DAYS = 825
_SKEW = dt.timedelta(minutes=5)  # not-before this far in the past: clocks of different machines differ


class CertError(ValueError):
    """A certificate request that cannot be done as asked (bad role or id, missing CA, file exists)."""


class Identity(NamedTuple):
    """An issued certificate found in a directory."""

    role: str
    id: str
    cn: str
    cert: Path
    key: Path | None  # None when the key is not in the directory (e.g. the router's copy of client certs)


def cn_for(role: str, ident: str | None = None) -> str:
    """The certificate common name of an identity: ``<role>-<id>``, or ``<role>`` when the id is the role.

    :param role: one of :data:`ROLES`
    :param ident: the process id (protocol rules); None: the role itself (the learner's default id is "learner")
    """
    if role not in ROLES:
        raise CertError(f"role {role!r}: not one of {', '.join(ROLES)}")
    ident = role if ident is None else ident
    try:
        _check_id("id", ident)
        if not (ident.isascii() and ident.isprintable()):
            raise ValueError("not printable ASCII")  # the CN is also the leaf's DNS subjectAltName
    except ValueError:
        raise CertError(f"id {ident!r}: 1-64 printable ASCII characters without / * $ ? # or space") from None
    return _cn_of(role, ident)


def parse_cn(cn: str) -> tuple[str, str]:
    """(role, id) of a common name made by :func:`cn_for` (roles hold no ``-``, ids may)."""
    role, sep, ident = cn.partition("-")
    if role not in ROLES or (sep and not ident):
        raise CertError(f"common name {cn!r} is not <role>[-<id>] with a role in {', '.join(ROLES)}")
    ident = ident if sep else role
    if cn_for(role, ident) != cn:
        raise CertError(f"common name {cn!r}: write it as {cn_for(role, ident)!r}")
    return role, ident


def load_cert(path: Path):
    """The X.509 certificate in the PEM file ``path`` (:class:`CertError` if it is not one).

    :param path: the file.
    """
    try:
        return x509.load_pem_x509_certificate(Path(path).read_bytes())
    except ValueError as exc:
        raise CertError(f"{path}: not a PEM certificate ({exc})") from None


def _cn(cert) -> str:
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not names:
        raise CertError("certificate has no common name")
    return str(names[0].value)


def common_name(path: str | os.PathLike) -> str:
    """The common name (CN) of the PEM certificate at ``path``."""
    return _cn(load_cert(Path(path)))


def expires(path: str | os.PathLike) -> dt.datetime:
    """When the PEM certificate at ``path`` stops being valid (UTC)."""
    return load_cert(Path(path)).not_valid_after_utc


def _secure_dir(path: Path) -> None:
    if not path.exists():
        path.mkdir(parents=True, mode=0o700)
        path.chmod(0o700)  # mkdir's mode is subject to the umask
    elif not path.is_dir():
        raise CertError(f"{path} exists and is not a directory")


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write ``data`` to ``path`` with ``mode`` from the start (never readable by others, even briefly), then
    rename it into place."""
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _refuse_existing(paths: Sequence[Path], what: str, force: bool) -> None:
    found = [str(p) for p in paths if p.exists()]
    if found and not force:
        raise CertError(f"{what} exists ({', '.join(found)}); use --force to replace it")


def _save(cert, key, cert_path: Path, key_path: Path) -> None:
    """The key as unencrypted PKCS#8 PEM (mode 0600) and the certificate as PEM (0644)."""
    _write(key_path, key.private_bytes(ser.Encoding.PEM, ser.PrivateFormat.PKCS8, ser.NoEncryption()), 0o600)
    _write(cert_path, cert.public_bytes(ser.Encoding.PEM), 0o644)


def _usage(*, ca: bool):
    """Key usage: a CA signs certificates and CRLs, a leaf signs its TLS handshakes."""
    return x509.KeyUsage(digital_signature=not ca, content_commitment=False, key_encipherment=False,
                         data_encipherment=False, key_agreement=False, key_cert_sign=ca, crl_sign=ca,
                         encipher_only=False, decipher_only=False)


def _name(cn: str):
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "KhGRL"),
                      x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _builder(subject, issuer, public_key, days: int, not_after_max: dt.datetime | None = None):
    if days < 1:
        raise CertError(f"days must be >= 1, got {days}")
    now = dt.datetime.now(dt.timezone.utc)
    not_after = now + dt.timedelta(days=days)
    if not_after_max is not None:
        not_after = min(not_after, not_after_max)  # a leaf never outlives its CA
    return (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer).public_key(public_key)
            .serial_number(x509.random_serial_number()).not_valid_before(now - _SKEW).not_valid_after(not_after)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(public_key), critical=False))


def init_ca(dir: str | os.PathLike, *, days: int = DEFAULT_DAYS, force: bool = False) -> tuple[Path, Path]:
    """Make a CA in ``dir``: ``ca.pem`` (certificate) and ``ca.key`` (private key, mode 0600).

    :param dir: the certificate directory (created mode 0700)
    :param days: validity
    :param force: replace an existing CA (every certificate it issued then stops being accepted)
    :return: (certificate path, key path)
    """
    d = Path(dir)
    cert_path, key_path = d / CA_CERT, d / CA_KEY
    _refuse_existing([cert_path, key_path], "a CA", force)
    _secure_dir(d)
    key = ec.generate_private_key(ec.SECP256R1())
    name = _name(f"KhGRL CA {dt.date.today().isoformat()} {secrets.token_hex(4)}")
    cert = (_builder(name, name, key.public_key(), days)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(_usage(ca=True), critical=True)
            .sign(key, hashes.SHA256()))
    _save(cert, key, cert_path, key_path)
    return cert_path, key_path


def _load_ca(d: Path):
    cert_path, key_path = d / CA_CERT, d / CA_KEY
    if not cert_path.is_file() or not key_path.is_file():
        raise CertError(f"no CA in {d} (need {CA_CERT} and {CA_KEY}); make one with: khgrl certs init {d}")
    try:
        key = ser.load_pem_private_key(key_path.read_bytes(), password=None)
    except (ValueError, TypeError) as exc:
        raise CertError(f"{key_path}: cannot read the CA key ({exc})") from None
    return load_cert(cert_path), key


def _sans(cn: str, hosts: Sequence[str]) -> list:
    out: list = [x509.DNSName(cn)]
    for h in hosts:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            try:
                out.append(x509.DNSName(h))
            except ValueError as exc:  # e.g. a non-ASCII name (write it as an A-label: xn--...)
                raise CertError(f"host {h!r}: not an IP address or DNS name ({exc})") from None
    return list(dict.fromkeys(out))


def issue(dir: str | os.PathLike, role: str, ident: str | None = None, *, hosts: Sequence[str] = (),
          days: int = DEFAULT_DAYS, force: bool = False) -> tuple[Path, Path]:
    """Make the key and certificate of one identity, signed by the CA in ``dir``: ``<cn>.pem`` and ``<cn>.key``
    (mode 0600), CN per :func:`cn_for`.

    :param dir: the certificate directory holding ``ca.pem`` and ``ca.key``
    :param role: one of :data:`ROLES`
    :param ident: the process id (None: the role itself)
    :param hosts: for the router only: the IP addresses and DNS names clients connect to (default 127.0.0.1 and
        localhost); other roles never get them, so no client certificate can pass for the router
    :param days: validity (cut to the CA's)
    :param force: replace an existing certificate of this identity
    :return: (certificate path, key path)
    """
    cn = cn_for(role, ident)
    if hosts and role != "router":
        raise CertError(f"hosts are for router certificates only (got {', '.join(hosts)} for {cn})")
    d = Path(dir)
    ca_cert, ca_key = _load_ca(d)
    if ca_cert.not_valid_after_utc <= dt.datetime.now(dt.timezone.utc):
        raise CertError(f"the CA in {d} expired on {ca_cert.not_valid_after_utc:%Y-%m-%d}; make a new one (--force)")
    cert_path, key_path = d / f"{cn}.pem", d / f"{cn}.key"
    _refuse_existing([cert_path, key_path], f"identity {cn}", force)
    key = ec.generate_private_key(ec.SECP256R1())
    sans = _sans(cn, (tuple(hosts) or DEFAULT_HOSTS) if role == "router" else ())
    cert = (_builder(_name(cn), ca_cert.subject, key.public_key(), days, ca_cert.not_valid_after_utc)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(_usage(ca=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .sign(ca_key, hashes.SHA256()))
    _save(cert, key, cert_path, key_path)
    return cert_path, key_path


def _identity(path: Path, ca) -> Identity | None:
    try:
        cert = load_cert(path)
        bc = cert.extensions.get_extension_for_class(x509.BasicConstraints).value
        role, ident = parse_cn(_cn(cert))
    except (CertError, x509.ExtensionNotFound):
        return None
    if bc.ca:
        return None
    if ca is not None:
        try:
            cert.verify_directly_issued_by(ca)
        except (InvalidSignature, ValueError, TypeError):  # another CA, or another key type
            return None
    key = path.with_suffix(".key")
    return Identity(role, ident, _cn(cert), path, key if key.is_file() else None)


def identities(dir: str | os.PathLike) -> list[Identity]:
    """The identities whose certificates are in ``dir`` (read from the certificates, not the file names): leaf
    certificates with a ``<role>[-<id>]`` common name, issued by the directory's CA when it has one
    (``ca.pem``), in role order then by id.

    :param dir: the certificate directory
    """
    d = Path(dir)
    if not d.is_dir():
        raise CertError(f"{d}: no such directory")
    ca = load_cert(d / CA_CERT) if (d / CA_CERT).is_file() else None
    found = [i for p in sorted(d.glob("*.pem")) if p.name != CA_CERT and (i := _identity(p, ca)) is not None]
    return sorted(found, key=lambda i: (ROLES.index(i.role), i.id))


def tls_settings(dir_or_paths: str | os.PathLike | tuple, cn: str | None = None, *, listen: bool) -> dict[str, Any]:
    """Zenoh's ``transport/link/tls`` settings for one identity, with mutual TLS: insert them with
    ``conf.insert_json5("transport/link/tls", json.dumps(settings))`` (on both sides: a client without
    ``enable_mtls`` sends no certificate).

    :param dir_or_paths: the certificate directory (``ca.pem``, ``<cn>.pem``, ``<cn>.key``), or a tuple
        (CA certificate, certificate, key) of paths
    :param cn: the identity's common name (needed with a directory; with paths, checked against the certificate)
    :param listen: True for the listening side (the router), False for a connecting client
    """
    if isinstance(dir_or_paths, tuple):
        ca, cert, key = (Path(p) for p in dir_or_paths)
    else:
        if cn is None:
            raise CertError("tls_settings: a common name is needed with a directory")
        d = Path(dir_or_paths)
        ca, cert, key = d / CA_CERT, d / f"{cn}.pem", d / f"{cn}.key"
    for p in (ca, cert, key):
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such file (make certificates with khgrl certs)")
    if cn is not None and common_name(cert) != cn:
        raise CertError(f"{cert}: common name {common_name(cert)!r}, expected {cn!r}")
    side = "listen" if listen else "connect"
    return {"root_ca_certificate": str(ca.resolve()), "enable_mtls": True,
            f"{side}_certificate": str(cert.resolve()), f"{side}_private_key": str(key.resolve()),
            "verify_name_on_connect": True}

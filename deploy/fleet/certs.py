"""A fleet's certificates: one private CA, one certificate and key per role.

Every zenoh link between hosts is mutual TLS (``enable_mtls``): both ends show a
certificate signed by the fleet's CA, so a machine without one cannot join. The
certificate's common name is the node's role (``leader``, ``plant``,
``agent-2``, ``bridge-2``, ``launcher``, ``router``): zenoh's access control
matches remote peers by it (``cert_common_names``), so the name *is* the
identity the ACL of :mod:`deploy.fleet.acl` is written for.

Keys are EC P-256 (small, fast handshakes on a robot's computer). Certificates
carry both serverAuth and clientAuth (a zenoh peer both listens and connects)
and, as subject alternative names, the role, ``localhost``, 127.0.0.1 and the
addresses of the role's machine, so that ``verify_name_on_connect`` holds for
every endpoint a peer is reached on (gossip hands out the listen addresses).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

CA_NAME = "ca"


@dataclass(frozen=True)
class RoleFiles:
    """Where one role's TLS material lives."""

    ca: Path  # the fleet CA's certificate (public)
    cert: Path
    key: Path


def role_files(cert_dir: str | Path, role: str) -> RoleFiles:
    d = Path(cert_dir)
    return RoleFiles(d / f"{CA_NAME}.pem", d / f"{role}.pem", d / f"{role}.key")


def _key():
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _write_key(path: Path, key) -> None:
    from cryptography.hazmat.primitives import serialization

    data = key.private_bytes(serialization.Encoding.PEM,
                             serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)  # private: owner only
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _write_cert(path: Path, cert) -> None:
    from cryptography.hazmat.primitives import serialization

    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _sans(role: str, addresses: Iterable[str]):
    from cryptography import x509

    names: list = [x509.DNSName(role), x509.DNSName("localhost"),
                   x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    for a in addresses:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(a)))
        except ValueError:
            names.append(x509.DNSName(a))
    seen, unique = set(), []
    for n in names:
        if n not in seen:
            seen.add(n)
            unique.append(n)
    return x509.SubjectAlternativeName(unique)


def make_ca(out: Path, fleet: str, days: int):
    """A self-signed CA for the fleet; returns (certificate, key)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    key = _key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"omnifleet {fleet} CA")])
    now = dt.datetime.now(dt.UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    _write_cert(out / f"{CA_NAME}.pem", cert)
    _write_key(out / f"{CA_NAME}.key", key)
    return cert, key


def make_role_cert(out: Path, role: str, ca_cert, ca_key, addresses: Iterable[str] = (),
                   days: int = 365) -> RoleFiles:
    """Certificate + key of one role (common name = role), signed by the CA."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = _key()
    now = dt.datetime.now(dt.UTC)
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, role)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(_sans(role, addresses), critical=False)
            .sign(ca_key, hashes.SHA256()))
    files = role_files(out, role)
    _write_cert(files.cert, cert)
    _write_key(files.key, key)
    return files


def make_fleet_certs(out: str | Path, fleet: str, roles: Mapping[str, Iterable[str]],
                     days: int = 365) -> dict[str, RoleFiles]:
    """A new CA in ``out`` and one certificate per role; ``roles`` maps each role
    to the addresses its machine is reached on (subject alternative names).

    The CA's private key (``ca.key``) stays with whoever makes the certificates;
    each machine gets ``ca.pem`` and its own roles' ``.pem``/``.key`` only."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ca_cert, ca_key = make_ca(out, fleet, days)
    return {role: make_role_cert(out, role, ca_cert, ca_key, addrs, days)
            for role, addrs in roles.items()}


def common_name(cert_path: str | Path) -> str:
    """The common name a certificate file presents (what the ACL matches)."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    cert = x509.load_pem_x509_certificate(Path(cert_path).read_bytes())
    return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value

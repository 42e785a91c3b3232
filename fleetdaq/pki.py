"""The site's certificates: one CA per site, the hub's router certificate, one per node (CN = the
node's name) and one per operator (CN = ``operator:NAME``, the role in the OU). Made with the
`cryptography` library; ECDSA P-256 keys (what rustls, Zenoh's TLS, prefers).

Layout of a PKI folder (keys 0600, the folder 0700)::

    ca.crt  ca.key                    the site CA (keep ca.key off the fleet: only `issue` needs it)
    hub.crt hub.key                   the hub's router (server and client: routers mesh)
    partitions/<name>.crt  .key       one per partition hub's router (CN ``hub:<name>``)
    nodes/<node>.crt  .key            one per edge
    operators/<name>.crt  .key        one per person using the CLI

Nothing is ever overwritten without ``force``. Mutual TLS and the access control list built from
these names are in `fleetdaq.runtime.zenoh_session` and `fleetdaq.hub.routing.acl`.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from fleetdaq.contract.keys import HUB
from fleetdaq.runtime.security import OPERATOR_CN_PREFIX, PARTITION_CN_PREFIX, check_private_file

Role = Literal["view", "control"]
NAME = re.compile(r"^[a-z][a-z0-9_-]{0,62}$")
CA_DAYS = 3650
LEAF_DAYS = 825


class PkiError(ValueError):
    """A one-line reason (no traceback for the person at the terminal)."""


@dataclass(frozen=True)
class Issued:
    cn: str
    cert: Path
    key: Path
    not_after: dt.datetime


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def _write(path: Path, data: bytes, mode: int, force: bool) -> None:
    """Write atomically with `mode` from the start (a key is never readable by others, even for
    a moment); refuse to replace an existing file unless `force`."""
    if path.exists() and not force:
        raise PkiError(f"{path} exists (use --force to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.chmod(tmp, mode)  # umask may have narrowed it; never widened
    os.replace(tmp, path)


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _name(cn: str, site: str, ou: str | None = None) -> x509.Name:
    attrs = [
        x509.NameAttribute(NameOID.ORGANIZATION_NAME, f"fleetdaq site {site}"),
        x509.NameAttribute(NameOID.COMMON_NAME, cn),
    ]
    if ou:
        attrs.insert(1, x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, ou))
    return x509.Name(attrs)


def _load_ca(folder: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert_path, key_path = folder / "ca.crt", folder / "ca.key"
    if not cert_path.exists() or not key_path.exists():
        raise PkiError(f"no site CA in {folder} (run `fleetdaq pki init` first)")
    check_private_file(key_path)
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise PkiError(f"{key_path} is not an EC private key")
    return cert, key


def site_of(ca: x509.Certificate) -> str:
    org = ca.subject.get_attributes_for_oid(NameOID.ORGANIZATION_NAME)
    value = str(org[0].value) if org else ""
    return value.removeprefix("fleetdaq site ")


def _leaf(
    folder: Path,
    cn: str,
    stem: Path,
    days: int,
    force: bool,
    server_names: list[str] | None = None,
    ou: str | None = None,
) -> Issued:
    ca_cert, ca_key = _load_ca(folder)
    key = _key()
    now = _now()
    not_after = min(now + dt.timedelta(days=days), ca_cert.not_valid_after_utc)
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(cn, site_of(ca_cert), ou))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(True, False, False, False, False, False, False, False, False),
            critical=True,
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
            critical=False,
        )
    )
    if server_names:
        usages.insert(0, ExtendedKeyUsageOID.SERVER_AUTH)
        alt: list[x509.GeneralName] = []
        for n in server_names:
            try:
                alt.append(x509.IPAddress(ipaddress.ip_address(n)))
            except ValueError:
                alt.append(x509.DNSName(n))
        builder = builder.add_extension(x509.SubjectAlternativeName(alt), critical=False)
    builder = builder.add_extension(x509.ExtendedKeyUsage(usages), critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())
    cert_path, key_path = stem.with_suffix(".crt"), stem.with_suffix(".key")
    for p in (cert_path, key_path):
        if p.exists() and not force:
            raise PkiError(f"{p} exists (use --force to replace it)")
    _write(key_path, _key_pem(key), 0o600, force)
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644, force)
    return Issued(cn, cert_path, key_path, not_after)


def init(
    folder: Path, site: str, hub_names: list[str] | None = None, days: int = CA_DAYS,
    force: bool = False,
) -> list[Issued]:  # fmt: skip
    """The site CA and the hub's router certificate (valid for `hub_names`: the host names and
    addresses edges connect to; default this machine's name, localhost and 127.0.0.1)."""
    for p in (folder / "ca.crt", folder / "ca.key"):
        if p.exists() and not force:
            raise PkiError(f"{p} exists: this folder already has a site CA (--force replaces it)")
    folder.mkdir(parents=True, exist_ok=True, mode=0o700)
    key = _key()
    now = _now()
    name = _name(f"fleetdaq {site} CA", site)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write(folder / "ca.key", _key_pem(key), 0o600, force)
    _write(folder / "ca.crt", cert.public_bytes(serialization.Encoding.PEM), 0o644, force)
    ca = Issued(f"fleetdaq {site} CA", folder / "ca.crt", folder / "ca.key", now)
    names = hub_names or _this_machine()
    hub = _leaf(folder, HUB, folder / HUB, LEAF_DAYS, force, server_names=names)
    return [ca, hub]


def _this_machine() -> list[str]:
    return [socket.gethostname(), "localhost", "127.0.0.1"]


def server_names(cert_path: Path) -> list[str]:
    """The host names and addresses a router certificate is valid for, in its order ([] when
    there is none, or it cannot be read)."""
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except (OSError, ValueError, x509.ExtensionNotFound):
        return []
    return [str(n.value) for n in san if isinstance(n, x509.DNSName | x509.IPAddress)]


def issue_hub(
    folder: Path, hub_names: list[str] | None = None, days: int = LEAF_DAYS, force: bool = False
) -> tuple[Issued, list[str]]:
    """The main hub's router pair again, signed by the site CA already there: its certificate
    ends (or names a host the hub no longer has) while the CA goes on. The nodes keep their
    pairs and ca.crt; only the hub's machine gets the new pair. Valid for `hub_names`, or the
    names of the hub.crt it replaces (a renewal), or this machine's when there is none.
    Returns the pair and the names it is valid for."""
    names = hub_names or server_names(folder / "hub.crt") or _this_machine()
    return _leaf(folder, HUB, folder / HUB, days, force, server_names=names), names


def issue_node(folder: Path, node: str, days: int = LEAF_DAYS, force: bool = False) -> Issued:
    if not NAME.match(node) or node == HUB:
        raise PkiError(f"{node!r} is not a node name (lowercase letters, digits, '-', '_')")
    return _leaf(folder, node, folder / "nodes" / node, days, force)


def issue_partition(
    folder: Path, name: str, hub_names: list[str], days: int = LEAF_DAYS, force: bool = False
) -> Issued:
    """Partition hub `name`'s router pair (CN ``hub:NAME``): a server for its nodes (valid for
    `hub_names`, the names and addresses they and the other hubs connect to) and a client of
    the routers it meshes with. The access control list grants it its own nodes' keys only."""
    if not NAME.match(name):
        raise PkiError(f"{name!r} is not a partition name (lowercase letters, digits, '-', '_')")
    if not hub_names:
        raise PkiError(f"partition hub {name}: no host name or address to make it valid for")
    stem = folder / "partitions" / name
    return _leaf(folder, PARTITION_CN_PREFIX + name, stem, days, force, server_names=hub_names)


def issue_operator(
    folder: Path, name: str, role: Role = "view", days: int = LEAF_DAYS, force: bool = False
) -> Issued:
    if not NAME.match(name):
        raise PkiError(f"{name!r} is not an operator name (lowercase letters, digits, '-', '_')")
    if role not in ("view", "control"):
        raise PkiError(f"role {role!r} is not view or control")
    cn = OPERATOR_CN_PREFIX + name
    return _leaf(folder, cn, folder / "operators" / name, days, force, ou=f"role={role}")


@dataclass(frozen=True)
class CertInfo:
    path: Path
    cn: str
    role: str
    not_after: dt.datetime
    fingerprint: str
    issued_by_site_ca: bool


def listing(folder: Path) -> list[CertInfo]:
    """Every certificate in the folder, checked against its CA."""
    ca = x509.load_pem_x509_certificate((folder / "ca.crt").read_bytes())
    out = []
    found = [
        folder / "hub.crt",
        *folder.glob("partitions/*.crt"),
        *folder.glob("nodes/*.crt"),
        *folder.glob("operators/*.crt"),
    ]
    for p in sorted(found):
        if not p.exists():
            continue
        cert = x509.load_pem_x509_certificate(p.read_bytes())
        cn = str(cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)
        ous = cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)
        role = str(ous[0].value).removeprefix("role=") if ous else ""
        try:
            cert.verify_directly_issued_by(ca)
            ours = True
        except (ValueError, TypeError, InvalidSignature):
            ours = False
        out.append(
            CertInfo(
                p,
                cn,
                role,
                cert.not_valid_after_utc,
                cert.fingerprint(hashes.SHA256()).hex(":")[:47],
                ours,
            )
        )
    return out


def operator_name(cert: Path) -> str:
    """NAME from an operator certificate's ``operator:NAME`` common name."""
    c = x509.load_pem_x509_certificate(cert.read_bytes())
    cns = c.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    cn = str(cns[0].value) if cns else ""
    if not cn.startswith(OPERATOR_CN_PREFIX):
        raise PkiError(f"{cert} is not an operator's certificate (its name is {cn!r})")
    return cn.removeprefix(OPERATOR_CN_PREFIX)


def operator_again(cert: Path) -> str:
    """The command that makes operator `cert`'s pair again: its name and the role it was made
    with (a template when the file is not an operator's certificate)."""
    try:
        c = x509.load_pem_x509_certificate(cert.read_bytes())
        name = operator_name(cert)
    except (OSError, ValueError, PkiError):
        return "fleetdaq pki issue NAME --operator --role ROLE --force"
    ous = c.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)
    role = str(ous[0].value).removeprefix("role=") if ous else "view"
    return f"fleetdaq pki issue {name} --operator --role {role} --force"

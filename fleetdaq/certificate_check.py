"""``fleetdaq pki check``: the certificates one machine connects with, as that machine holds
them (``security.pki_dir``): the site CA and its own pairs, each judged now. `fleetdaq fleet
status` runs it on every host, so it also sees a node the hub has not heard since it started.

For each: its dates (ending within ``certificate_expiring``'s days, ended, or not started yet by
this machine's clock), whether the CA beside it issued it (after ``pki init --force`` a pair
not re-issued is refused by the hub), and the command that fixes what is wrong. Private keys are
not read: they belong to the service's user, not to whoever checks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, NotRequired, TypedDict

from fleetdaq.runtime.certificate_dates import (
    DAY_NS,
    HUB_AGAIN,
    ROTATE,
    node_again,
    partition_again,
    utc_text,
    warn_days,
    when_it_ends,
)
from fleetdaq.runtime.security import read_certificate

if TYPE_CHECKING:
    from cryptography import x509

    from fleetdaq.contract.config.site import SiteConfig


class CertificateState(StrEnum):
    """A certificate's state as judged on one machine (its JSON value is the string)."""

    OK = "ok"
    NOT_PERMITTED = "not_permitted"
    EXPIRING = "expiring"
    EXPIRED = "expired"
    NOT_YET_VALID = "not_yet_valid"
    FOREIGN = "foreign"
    UNREADABLE = "unreadable"


STATES = tuple(CertificateState)
"""From fine to worst. ``not_permitted``: whoever checks may not read it (the PKI folder is the
services' own, 0750), which says nothing of the host; the rest are something to fix."""

GOOD = (CertificateState.OK, CertificateState.NOT_PERMITTED)
"""States that are not the host's fault."""

_ROTATE = f"rotate: {ROTATE}, re-issue every pair, copy them out, restart"
_HUB_AGAIN = (
    f"{HUB_AGAIN} (the same CA: the nodes keep their pairs), copy hub.crt and hub.key here, "
    "restart the hub"
)


@dataclass(frozen=True, slots=True)
class Checked:
    """One certificate as judged on this machine."""

    which: str
    """``ca``, ``hub``, ``partition NAME`` or ``node NAME``."""
    path: str
    state: CertificateState
    cn: str = ""
    not_before_ns: int = 0
    not_after_ns: int = 0
    days_left: float | None = None
    fingerprint: str = ""
    """SHA-256 of the certificate (hex): hosts holding different site CAs differ here."""
    message: str = ""
    """What is wrong and how to fix it ("" when ok)."""


class CheckedJson(TypedDict):
    """A `Checked` in ``pki check --json`` (what `fleetdaq fleet status` reads back)."""

    which: str
    path: str
    state: str
    cn: str
    not_before_ns: int
    not_after_ns: int
    days_left: float | None
    fingerprint: str
    message: str


class CheckReport(TypedDict):
    """What ``pki check --json`` prints; only `tls` when TLS is off."""

    tls: bool
    pki_dir: NotRequired[str]
    warn_days: NotRequired[float]
    now_ns: NotRequired[int]
    first_not_after_ns: NotRequired[int]
    certificates: NotRequired[list[CheckedJson]]
    problems: NotRequired[list[str]]
    unchecked: NotRequired[list[str]]


def _json(c: Checked) -> CheckedJson:
    return {
        "which": c.which,
        "path": c.path,
        "state": c.state,
        "cn": c.cn,
        "not_before_ns": c.not_before_ns,
        "not_after_ns": c.not_after_ns,
        "days_left": c.days_left,
        "fingerprint": c.fingerprint,
        "message": c.message,
    }


def _load(path: Path) -> x509.Certificate | None:
    """The certificate at `path` (a cryptography x509.Certificate), or None."""
    from cryptography import x509

    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except (OSError, ValueError):
        return None


def _issued_by(cert: x509.Certificate | None, ca_path: Path) -> bool | None:
    """Whether the CA at `ca_path` signed `cert`; None when either cannot be read."""
    from cryptography.exceptions import InvalidSignature

    ca = _load(ca_path)
    if cert is None or ca is None:
        return None
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


def judge(
    which: str, path: Path, fix: str, ca: Path | None, now_ns: int, days_before: float
) -> Checked:
    """One certificate: `ca` is the CA that should have issued it (None for the CA itself)."""
    from cryptography.hazmat.primitives import hashes

    try:
        path.open("rb").close()
    except PermissionError as err:
        return Checked(
            which,
            str(path),
            CertificateState.NOT_PERMITTED,
            message=f"not checked: this user may not read it ({err.strerror}); run it as root "
            "or as a member of the services' group",
        )
    except OSError:
        pass  # read_certificate says what
    c = read_certificate(path)
    if "error" in c:
        copy = "copy the site's ca.crt here" if ca is None else fix
        return Checked(
            which, str(path), CertificateState.UNREADABLE, message=f"{c['error']} ({copy})"
        )
    days = round((c["not_after_ns"] - now_ns) / DAY_NS, 2)
    cert = _load(path)
    base = Checked(
        which,
        str(path),
        CertificateState.OK,
        cn=c["cn"],
        not_before_ns=c["not_before_ns"],
        not_after_ns=c["not_after_ns"],
        days_left=days,
        fingerprint=cert.fingerprint(hashes.SHA256()).hex() if cert is not None else "",
    )
    if ca is not None and _issued_by(cert, ca) is False:
        state, message = (
            CertificateState.FOREIGN,
            f"not issued by the site CA {ca} beside it: the hub refuses it "
            f"(an old pair from before a rotation, or another site's; {fix})",
        )
    elif now_ns < base.not_before_ns:
        state, message = (
            CertificateState.NOT_YET_VALID,
            f"starts on {utc_text(base.not_before_ns)}, and this machine's clock says "
            f"{utc_text(now_ns)}: TLS refuses it until the clock is set (PTP or NTP; a Pi without "
            "a real-time clock boots with an old date)",
        )
    elif days <= 0:
        state, message = (
            CertificateState.EXPIRED,
            f"{when_it_ends(base.not_after_ns, now_ns)} ({fix})",
        )
    elif days < days_before:
        state, message = (
            CertificateState.EXPIRING,
            f"{when_it_ends(base.not_after_ns, now_ns)} ({fix})",
        )
    else:
        return base
    return replace(base, state=state, message=message)


def _pairs(
    pki: Path, nodes: tuple[str, ...], hub: bool, partitions: tuple[str, ...]
) -> list[tuple[str, Path, str]]:
    """(which, certificate, fix) of the pairs named, or of every pair in the folder."""
    named = bool(nodes or hub or partitions)
    if not named:
        hub = (pki / "hub.crt").exists()
        partitions = tuple(sorted(p.stem for p in pki.glob("partitions/*.crt")))
        nodes = tuple(sorted(p.stem for p in pki.glob("nodes/*.crt")))
    out = [("hub", pki / "hub.crt", _HUB_AGAIN)] if hub else []
    out += [
        (f"partition {p}", pki / "partitions" / f"{p}.crt",
         f"{partition_again(p)}, copy it, restart")
        for p in partitions
    ]  # fmt: skip
    out += [
        (f"node {n}", pki / "nodes" / f"{n}.crt",
         f"{node_again(n)}, copy it, restart the edge")
        for n in nodes
    ]  # fmt: skip
    return out


def check(
    site: SiteConfig,
    nodes: tuple[str, ...] = (),
    hub: bool = False,
    partitions: tuple[str, ...] = (),
    now_ns: int | None = None,
) -> CheckReport:
    """What ``pki check --json`` prints. Without TLS: ``{"tls": false}``."""
    if not site.security.tls:
        return {"tls": False}
    now_ns = time.time_ns() if now_ns is None else now_ns
    pki = Path(site.security.pki_dir)
    days = warn_days(site)
    ca = pki / "ca.crt"
    found = [judge("ca", ca, _ROTATE, None, now_ns, days)]
    pairs = _pairs(pki, nodes, hub, partitions)
    found += [judge(which, path, fix, ca, now_ns, days) for which, path, fix in pairs]
    problems = [f"{c.which} {c.path}: {c.message}" for c in found if c.state not in GOOD]
    unchecked = [
        f"{c.which} {c.path}: {c.message}"
        for c in found
        if c.state is CertificateState.NOT_PERMITTED
    ]
    if not pairs:
        problems.append(
            f"no certificate pair in {pki} (fleetdaq pki issue NODE; copy the pair here)"
        )
    ends = [c.not_after_ns for c in found]
    return {
        "tls": True,
        "pki_dir": str(pki),
        "warn_days": days,
        "now_ns": now_ns,
        "first_not_after_ns": min(ends) if all(ends) else 0,
        "certificates": [_json(c) for c in found],
        "problems": problems,
        "unchecked": unchecked,
    }

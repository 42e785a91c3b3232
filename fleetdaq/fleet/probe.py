"""One host's status over one SSH connection: its facts (`facts`), ``fleetdaq --version``,
``fleetdaq ptp status --json``, ``fleetdaq pki check --json`` and, on the hub,
``fleetdaq rec status --json`` — each run by the host's own fleetdaq, so what is reported is
what the host itself sees. A host whose answer is partial (fleetdaq missing, a command timing
out, the link dropping) says what is missing.
"""

from __future__ import annotations

import json
import shlex
import time
from dataclasses import replace
from typing import Any, TypedDict

import paramiko

from fleetdaq.fleet.errors import CommandTimeout, SshError
from fleetdaq.fleet.facts import DirUsage, Facts, Unit, facts_script, parse_facts
from fleetdaq.fleet.host_status import (
    MIN_FREE_FRACTION,
    CertificatesView,
    HostStatus,
    RecorderView,
    TimeView,
)
from fleetdaq.fleet.inventory import Host
from fleetdaq.fleet.layout import HostLayout
from fleetdaq.fleet.ssh import Connection, SshOptions, connect

NO_OPERATOR_PAIR = "security.tls is on, but "
"""How `fleetdaq rec status` says it has no operator pair to ask the hub with."""
SET_PAIR = " (set FLEETDAQ_CERT and FLEETDAQ_KEY)"
OPERATOR_PAIR_NEEDED = (
    "on a TLS site the SSH user asks the hub as an operator: give that user on this host a "
    "view operator's pair (the inventory's fleetdaq_status_operator and the playbook, or "
    "fleetdaq pki issue NAME --operator --role view, NAME under security.operators, copied to "
    "~/.config/fleetdaq/operator.crt and operator.key there)"
)


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1] if lines else ""


def parse_version(stdout: str) -> str | None:
    """``fleetdaq, version 0.1.0`` (click's --version) -> ``0.1.0``."""
    _, sep, version = stdout.strip().rpartition("version ")
    return version.strip() or None if sep else None


def parse_time(stdout: str, expected: bool) -> TimeView:
    """``fleetdaq ptp status --json`` -> `TimeView`. Raises ValueError on anything else."""
    from fleetdaq.ptp.time_status import TimeStatus

    try:
        data = json.loads(stdout)
        status = TimeStatus.from_dict(data)
    except (KeyError, TypeError, json.JSONDecodeError) as err:
        raise ValueError(f"not a time status: {err}") from err
    counted = [c for c in status.checks if c.name not in status.ignored]
    worst = max(counted, key=lambda c: c.level, default=None)
    message = worst.message if worst is not None and worst.level > 0 else ""
    return TimeView(
        state=status.state.value,
        level=status.level.name.lower(),
        offset_ns=status.offset_ns,
        grandmaster_id=status.grandmaster_id,
        is_grandmaster=status.is_grandmaster,
        message=message,
        expected=expected,
    )


def parse_certificates(stdout: str) -> CertificatesView:
    """``fleetdaq pki check --json`` -> `CertificatesView`. Raises ValueError on anything else."""
    from fleetdaq.certificate_check import STATES, CheckReport
    from fleetdaq.runtime.certificate_dates import DAY_NS

    try:
        # Unchecked as it comes (another host's fleetdaq wrote it): a field missing or of
        # another type raises below, and is refused as not a certificate check.
        d: CheckReport = json.loads(stdout)
        if not d["tls"]:
            return CertificatesView(tls=False)
        now_ns, first = int(d["now_ns"]), int(d["first_not_after_ns"])
        found = d["certificates"]
        ca = next((c for c in found if c["which"] == "ca"), None)
        return CertificatesView(
            tls=True,
            first_not_after_ns=first,
            days_left=round((first - now_ns) / DAY_NS, 2) if first else None,
            ca_fingerprint=str(ca.get("fingerprint", "")) if ca is not None else "",
            worst=max((str(c["state"]) for c in found), key=STATES.index, default="ok"),
            problems=tuple(str(p) for p in d["problems"]),
            unchecked=tuple(str(p) for p in d.get("unchecked", ())),
            pki_dir=str(d.get("pki_dir", "")),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise ValueError(f"not a certificate check: {err}") from err


def parse_recorder(stdout: str) -> RecorderView:
    """``fleetdaq rec status --json`` -> `RecorderView`. Raises ValueError on anything else."""
    try:
        r: dict[str, Any] = json.loads(stdout)["recorder"]
        return RecorderView(
            state=str(r["state"]),
            session=r.get("session") or None,
            current_file=r.get("current_file") or None,
            current_file_bytes=int(r.get("current_file_bytes") or 0),
            write_errors=int(r.get("write_errors") or 0),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"not a recorder status: {err}") from err


class _Learnt(TypedDict, total=False):
    """What a probe learnt of a host: the `HostStatus` fields it fills in."""

    uptime_s: float | None
    systemd: bool | None
    units: tuple[Unit, ...]
    dirs: tuple[DirUsage, ...]
    version: str | None
    time: TimeView | None
    certificates: CertificatesView | None
    recorder: RecorderView | None


class _Probe:
    """The steps of one host's probe; each adds what it learnt or the problem it met."""

    def __init__(self, host: Host, layout: HostLayout, conn: Connection, deadline: float) -> None:
        self.host, self.layout, self.conn, self.deadline = host, layout, conn, deadline
        self.problems: list[str] = []
        self.notes: list[str] = []
        self.fields: _Learnt = {}

    def run(self, *args: str, env: str = "") -> tuple[int, str, str]:
        """`args` on the host; `env`: ``NAME=value ...`` before them (a shell line)."""
        remaining = self.deadline - time.monotonic()
        if remaining <= 0:
            raise CommandTimeout(f"no time left for {args[-1]}")
        result = self.conn.run(f"{env} {shlex.join(args)}" if env else shlex.join(args), remaining)
        return result.status, result.stdout, result.stderr

    def facts(self) -> Facts:
        r = self.conn.run(facts_script(self.layout), max(0.1, self.deadline - time.monotonic()))
        facts = parse_facts(r.stdout, self.layout)
        self.fields.update(
            {
                "uptime_s": facts.uptime_s,
                "systemd": facts.systemd,
                "units": facts.units,
                "dirs": facts.dirs,
            }
        )
        if not facts.systemd:
            self.notes.append("no systemd on this host: services not checked")
        for unit in facts.units:
            if not unit.ok:
                self.problems.append(f"{unit.name} is {unit.describe()}")
        for d in facts.dirs:
            if d.free_fraction is not None and d.free_fraction < MIN_FREE_FRACTION:
                self.problems.append(
                    f"{d.role} disk nearly full: {d.free_fraction:.1%} free at {d.path}"
                )
            if not d.exists:
                self.notes.append(f"no {d.role} directory yet at {d.path}")
        if not facts.site_file:
            self.problems.append(f"no site file at {self.layout.site_file}")
        if not facts.fleetdaq:
            self.problems.append(f"fleetdaq is not installed at {self.layout.fleetdaq}")
        return facts

    def version(self) -> None:
        status, out, err = self.run(self.layout.fleetdaq, "--version")
        version = parse_version(out) if status == 0 else None
        if version is None:
            self.problems.append(f"fleetdaq --version failed: {_last_line(err or out)}")
        self.fields["version"] = version

    def time(self, site_file: bool) -> None:
        args = [self.layout.fleetdaq, "ptp", "status", "--json"]
        if self.layout.ptp_source != "ptp4l":
            args += ["--source", self.layout.ptp_source]
        if self.host.is_edge and site_file:
            args += ["--config", self.layout.site_file, "--node", self.host.node]
        _, out, err = self.run(*args)
        try:
            view = parse_time(out, self.layout.ptp_expected)
        except ValueError:
            self.problems.append(f"fleetdaq ptp status failed: {_last_line(err or out)}")
            return
        self.fields["time"] = view
        if view.expected and view.level == "fail":
            self.problems.append(f"time: {view.state}: {view.message}")
        elif not view.expected and view.level != "ok":
            self.notes.append(f"time not set up here (no PTP in the inventory): {view.state}")

    def certificates(self) -> None:
        args = [self.layout.fleetdaq, "pki", "check", "--json", "--config", self.layout.site_file]
        if self.host.prefix:  # the site file's pki_dir is the services' path, under the prefix
            args += ["--root", self.host.prefix]
        if self.host.is_edge:
            args += ["--node", self.host.node]
        if self.host.is_hub:
            args += (
                ["--hub"] if self.host.partition is None else ["--partition", self.host.partition]
            )
        status, out, err = self.run(*args)
        try:
            view = parse_certificates(out)
        except ValueError:
            said = _last_line(err or out) or f"exit {status}"
            if "No such command" in said:  # a fleetdaq from before `pki check`
                self.notes.append("certificates not checked: this host's fleetdaq has no pki check")
            else:
                self.problems.append(f"certificates: {said}")
            return
        self.fields["certificates"] = view
        self.problems.extend(f"certificate: {p}" for p in view.problems)
        self.notes.extend(f"certificate {p}" for p in view.unchecked)

    def _operator_under_prefix(self) -> str:
        """With a prefix, the operator's files where the host's own would be under it: the
        login user's pair (``$HOME/.config/fleetdaq``) and the site CA beside the host's pairs."""
        if not self.host.prefix:
            return ""
        root = shlex.quote(self.host.prefix.rstrip("/"))
        env = f'XDG_CONFIG_HOME={root}"$HOME/.config"'
        certs = self.fields.get("certificates")
        if isinstance(certs, CertificatesView) and certs.pki_dir:
            env += f" FLEETDAQ_CA={shlex.quote(certs.pki_dir + '/ca.crt')}"
        return env

    def recorder(self) -> None:
        args = [self.layout.fleetdaq, "rec", "status", "--json", "--config", self.layout.site_file]
        if self.host.partition is not None:  # a partition hub's own recorder
            args += ["--partition", self.host.partition]
        status, out, err = self.run(*args, env=self._operator_under_prefix())
        # e.g. the SSH user's operator pair ends soon (the command still ran)
        self.notes.extend(
            f"rec status: {line.removeprefix('note: ')}"
            for line in err.splitlines()
            if line.startswith("note: ")
        )
        try:
            view = parse_recorder(out)
        except ValueError:
            said = _last_line(err or out) or f"exit {status}"
            if said.startswith(NO_OPERATOR_PAIR):
                said = f"not asked: {said.removesuffix(SET_PAIR)}; {OPERATOR_PAIR_NEEDED}"
            self.problems.append(f"recorder: {said}")
            return
        self.fields["recorder"] = view
        if view.write_errors:
            self.problems.append(f"recorder: {view.write_errors} write errors")


def probe(host: Host, layout: HostLayout, options: SshOptions, timeout: float) -> HostStatus:
    """The status of one host, never raising for anything the host or the network does."""
    base = HostStatus(
        host=host.name,
        address=host.address,
        port=host.port,
        roles=host.roles,
        node=host.node if host.is_edge else None,
    )
    deadline = time.monotonic() + timeout
    try:
        conn = connect(host, options, timeout)
    except SshError as err:
        return replace(base, unreachable=err, problems=(str(err),))
    with conn:
        p = _Probe(host, layout, conn, deadline)
        step = "facts"
        try:
            facts = p.facts()
            if facts.fleetdaq:
                step = "fleetdaq --version"
                p.version()
                step = "fleetdaq ptp status"
                p.time(facts.site_file)
                if facts.site_file:
                    step = "fleetdaq pki check"
                    p.certificates()
                if host.is_hub and facts.site_file:
                    step = "fleetdaq rec status"
                    p.recorder()
        except CommandTimeout:
            p.problems.append(f"timed out after {timeout:g} s at {step}")
        except (paramiko.SSHException, OSError, EOFError) as err:
            p.problems.append(f"connection lost at {step}: {err or type(err).__name__}")
    return replace(base, **p.fields, problems=tuple(p.problems), notes=tuple(p.notes))

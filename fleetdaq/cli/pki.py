"""``fleetdaq pki``: the site's certificates — `init` (the site CA and the hub's router
certificate), `hub` (that pair again, with the same CA), `issue NODE`, `issue NAME
--partition` (a partition hub's router) and `issue --operator NAME --role view|control`,
`list`, and `check` (the dates and issuer of the certificates one machine holds; `fleetdaq
fleet status` runs it on every host)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from fleetdaq.cli.common import fail, load_site

if TYPE_CHECKING:
    from fleetdaq.certificate_check import CheckReport


def _dir_option(f: click.decorators.FC) -> click.decorators.FC:
    return click.option(
        "--dir",
        "folder",
        type=click.Path(file_okay=False, path_type=Path),
        default=Path("pki"),
        show_default=True,
        help="The PKI folder (keep it, and ca.key above all, on the control machine).",
    )(f)


@click.group()
def pki() -> None:
    """The site's certificate authority and certificates (mutual TLS on every link)."""


@pki.command()
@_dir_option
@click.option("--config", "config", type=click.Path(), help="Site file (its site name).")
@click.option("--site", default=None, help="Site name, when no --config is given.")
@click.option(
    "--hub-name",
    "hub_names",
    multiple=True,
    help="A host name or address edges use to reach the hub (repeat; default: this machine's "
    "name, localhost, 127.0.0.1).",
)
@click.option("--days", default=3650, show_default=True, help="The CA's validity.")
@click.option("--force", is_flag=True, help="Replace an existing CA (every certificate with it).")
def init(
    folder: Path,
    config: str | None,
    site: str | None,
    hub_names: tuple[str, ...],
    days: int,
    force: bool,
) -> None:
    """Create the site CA and the hub's router certificate."""
    from fleetdaq.pki import PkiError, init
    from fleetdaq.runtime.security import SecretFileError

    if config:
        site = load_site(config).site
    if not site:
        fail("pki init: give --config SITE_FILE or --site NAME", 2)
    try:
        made = init(folder, site, list(hub_names) or None, days, force)
    except (PkiError, SecretFileError) as err:
        fail(f"pki init: {err}", 2)
    for m in made:
        click.echo(f"{m.cert}  ({m.cn}; key {m.key}, mode 0600)")
    click.echo(f"Next: fleetdaq pki issue NODE --dir {folder}, for every node of the site.")


@pki.command()
@_dir_option
@click.argument("name")
@click.option("--operator", is_flag=True, help="NAME is a person using the CLI, not a node.")
@click.option(
    "--partition",
    is_flag=True,
    help="NAME is a partition hub of the site file's hub.partitions: its router's own pair.",
)
@click.option(
    "--hub-name",
    "hub_names",
    multiple=True,
    help="With --partition: a host name or address its nodes and the other hubs reach it by "
    "(repeat; default: the hosts of its listen in --config, localhost, 127.0.0.1).",
)
@click.option(
    "--role",
    type=click.Choice(["view", "control"]),
    default="view",
    show_default=True,
    help="An operator's role: view (status, lists) or control (actions, outputs).",
)
@click.option("--config", "config", type=click.Path(), help="Site file: the node must be in it.")
@click.option("--days", default=825, show_default=True)
@click.option("--force", is_flag=True, help="Replace an existing certificate and key.")
def issue(
    folder: Path,
    name: str,
    operator: bool,
    partition: bool,
    hub_names: tuple[str, ...],
    role: str,
    config: str | None,
    days: int,
    force: bool,
) -> None:
    """Issue a certificate for a node (CN = its name), a partition hub or an operator."""
    from fleetdaq.pki import PkiError, issue_node, issue_operator, issue_partition
    from fleetdaq.runtime.security import SecretFileError

    if operator and partition:
        fail("pki issue: NAME is an operator or a partition hub, not both", 2)
    if hub_names and not partition:
        fail("pki issue: --hub-name is for a partition hub's pair (--partition)", 2)
    try:
        if partition:
            names = list(hub_names) or _partition_hosts(config, name)
            made = issue_partition(folder, name, names, days, force)
        elif operator:
            made = issue_operator(folder, name, role, days, force)  # type: ignore[arg-type]
        else:
            if config and name not in load_site(config).nodes:
                fail(f"pki issue: the site file {config} has no node {name!r}", 2)
            made = issue_node(folder, name, days, force)
    except (PkiError, SecretFileError) as err:
        fail(f"pki issue: {err}", 2)
    click.echo(f"{made.cert}  (CN {made.cn}, until {made.not_after:%Y-%m-%d}; key {made.key})")
    if operator:
        click.echo(
            f"Add to the site file: security: {{operators: {{{name}: {role}}}}}; restart the hub."
        )
    if partition:
        click.echo(f"Copy it, the key and ca.crt to partition hub {name}'s machine only.")


@pki.command("hub")
@_dir_option
@click.option(
    "--hub-name",
    "hub_names",
    multiple=True,
    help="A host name or address edges use to reach the hub (repeat; default: those of the "
    "hub.crt it replaces).",
)
@click.option("--days", default=825, show_default=True)
@click.option("--force", is_flag=True, help="Replace the hub's certificate and key.")
def hub_pair(folder: Path, hub_names: tuple[str, ...], days: int, force: bool) -> None:
    """Issue the main hub's router pair again with the site CA already there (its certificate
    ends, or the hub has a new name or address): the nodes keep their pairs and ca.crt."""
    from fleetdaq.pki import PkiError, issue_hub
    from fleetdaq.runtime.security import SecretFileError

    try:
        made, names = issue_hub(folder, list(hub_names) or None, days, force)
    except (PkiError, SecretFileError) as err:
        fail(f"pki hub: {err}", 2)
    click.echo(
        f"{made.cert}  (CN {made.cn}, until {made.not_after:%Y-%m-%d}, for {', '.join(names)}; "
        f"key {made.key})"
    )
    click.echo(
        "Copy hub.crt and hub.key to the hub's machine only (or run the playbook) and restart "
        "the hub; the nodes keep their pairs and ca.crt."
    )


def _partition_hosts(config: str | None, name: str) -> list[str]:
    """The hosts a partition hub is reached by: those of its `listen` (not a wildcard
    address), then localhost and 127.0.0.1."""
    if not config:
        fail(f"pki issue {name} --partition: give --config SITE_FILE or --hub-name HOST", 2)
    site = load_site(config)
    part = site.hub.partitions.get(name)
    if part is None:
        known = ", ".join(site.hub.partitions) or "none"
        fail(
            f"pki issue: the site file {config} has no partition {name!r} "
            f"(hub.partitions: {known})",
            2,
        )
    hosts = []
    for endpoint in part.listen:
        address = endpoint.split("#", 1)[0].split("?", 1)[0].split("/", 1)[-1]
        host = address.rsplit(":", 1)[0].strip("[]")
        if host not in ("0.0.0.0", "::", "") and host not in hosts:
            hosts.append(host)
    return hosts + [h for h in ("localhost", "127.0.0.1") if h not in hosts]


@pki.command("list")
@_dir_option
def list_certs(folder: Path) -> None:
    """Every certificate in the folder: CN, role, expiry, whether the site CA issued it."""
    from fleetdaq.pki import listing

    if not (folder / "ca.crt").exists():
        fail(f"pki list: no site CA in {folder}", 2)
    for c in listing(folder):
        mark = "" if c.issued_by_site_ca else "  NOT ISSUED BY THIS CA"
        role = f" role={c.role}" if c.role else ""
        click.echo(f"{c.cn:30} until {c.not_after:%Y-%m-%d}{role}  {c.path}{mark}")


@pki.command("acl")
@click.option("--config", "config", required=True, type=click.Path(), help="Site file.")
def acl(config: str) -> None:
    """The hub router's access control list made from the site file (JSON): what each
    certificate may do once security.tls is on."""
    import json

    from fleetdaq.hub.routing.acl import access_control

    click.echo(json.dumps(access_control(load_site(config)), indent=2))


@pki.command("check")
@click.option("--config", "config", required=True, type=click.Path(), help="Site file.")
@click.option("--node", "nodes", multiple=True, help="A node whose pair this machine holds.")
@click.option("--hub", is_flag=True, help="The main hub's pair (hub.crt).")
@click.option("--partition", "partitions", multiple=True, help="A partition hub's own pair.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object.")
@click.option(
    "--root",
    type=click.Path(file_okay=False),
    help="The folder the site file's paths are under (a chroot; fleet status's fleetdaq_prefix).",
)
def check_certs(
    config: str,
    nodes: tuple[str, ...],
    hub: bool,
    partitions: tuple[str, ...],
    as_json: bool,
    root: str | None,
) -> None:
    """The certificates this machine connects with (security.pki_dir): the site CA and the
    pairs named (every pair in the folder when none is), each checked for its dates (ending
    within certificate_expiring's days, ended, not started by this clock) and its issuer (the
    CA beside it). Exit 0 all fine, 1 something to fix or not readable by this user, 2 bad
    input."""
    import json

    from fleetdaq.certificate_check import check

    site = load_site(config)
    if root and Path(site.security.pki_dir).is_absolute():  # as the services see it, from outside
        pki_dir = Path(root) / Path(site.security.pki_dir).relative_to("/")
        security = site.security.model_copy(update={"pki_dir": str(pki_dir)})
        site = site.model_copy(update={"security": security})
    for n in nodes:
        if n not in site.nodes:
            fail(f"pki check: the site file {config} has no node {n!r}", 2)
    for p in partitions:
        if p not in site.hub.partitions:
            fail(f"pki check: the site file {config} has no partition hub {p!r}", 2)
    found = check(site, nodes, hub, partitions)
    if as_json:
        click.echo(json.dumps(found))
    elif not found["tls"]:
        click.echo(f"security.tls is off in {config}: the links use no certificates")
    else:
        _print_checked(found)
    sys.exit(1 if found.get("problems") or found.get("unchecked") else 0)


def _print_checked(found: CheckReport) -> None:
    import datetime as dt

    click.echo(f"{found['pki_dir']} (warning {found['warn_days']:g} days before the end)")
    for c in found["certificates"]:
        until = (
            f"until {dt.datetime.fromtimestamp(c['not_after_ns'] / 1e9, dt.UTC):%Y-%m-%d} "
            f"({c['days_left']:.0f} d)"
            if c["not_after_ns"]
            else "-"
        )
        click.echo(f"{c['which']:20} {c['state']:13} {until:26} {c['path']}")
    for p in found["problems"]:
        click.echo(f"✗ {p}")
    for p in found["unchecked"]:
        click.echo(f"? {p}")

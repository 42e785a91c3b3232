"""``fleetdaq demo``: the hub in this process and every node of a site as its own process."""

from __future__ import annotations

import json
from pathlib import Path

import click

from fleetdaq.cli.common import fail, finish, load_site, stop_on_signals


@click.command()
@click.option(
    "--config",
    "config",
    type=click.Path(),
    help="Site file (default: the embedded demo site).",
)
@click.option(
    "--data",
    "data_dir",
    type=click.Path(file_okay=False),
    help="Recording root (default: ~/.local/state/fleetdaq/demo, /var/lib/fleetdaq/demo as root).",
)
@click.option(
    "--duration",
    type=click.FloatRange(min=0, min_open=True),
    help="Run this many seconds, then stop (default: until Ctrl-C).",
)
@click.option("--json", "as_json", is_flag=True, help="Print a JSON summary at exit.")
@click.option("--listen", help="Hub endpoint, overriding the site file (e.g. tcp/127.0.0.1:7450).")
@click.option(
    "--dashboard",
    help="The dashboard's ADDRESS:PORT, overriding the site file (e.g. 127.0.0.1:8081; port 0: "
    "any free port), or 'off'.",
)
@click.option(
    "--foxglove",
    help="The Foxglove live view's ADDRESS:PORT, overriding the site file (port 0: any free "
    "port), or 'off'.",
)
def demo(
    config: str | None,
    data_dir: str | None,
    duration: float | None,
    as_json: bool,
    listen: str | None,
    dashboard: str | None,
    foxglove: str | None,
) -> None:
    """Hub + every node of the site as separate processes, with a live table.

    The dashboard is served as the site file says (http://127.0.0.1:8080/ for the demo site);
    the demo gives its user `demo` a new random password at each start and prints it."""
    from fleetdaq.contract.config.site import demo_config_path
    from fleetdaq.runtime.paths import default_demo_dir

    path = Path(config) if config else demo_config_path()
    site = load_site(path)
    if listen:
        from fleetdaq.contract.schema import check_endpoint

        try:
            check_endpoint(listen)
        except ValueError as err:
            fail(f"--listen: {err}")
    for option, value in (("--dashboard", dashboard), ("--foxglove", foxglove)):
        if value and value != "off":
            from fleetdaq.hub.config.dashboard import check_listen

            try:
                check_listen(value)
            except ValueError as err:
                fail(f"{option}: {err}")
    from fleetdaq.cli.demo_screen import run_demo
    from fleetdaq.hub.live.web.users import UsersFileError
    from fleetdaq.hub.recording.data_lock import DataFolderInUse
    from fleetdaq.runtime.writable import UnwritablePlace

    # The edges run in process groups of their own (a terminal's Ctrl-C or hangup reaches the
    # demo alone), so the demo stops them on either.
    stop = stop_on_signals(hangup=True)
    root = Path(data_dir) if data_dir else default_demo_dir()
    try:
        code, summary = run_demo(site, path, root, duration, stop, listen, dashboard, foxglove)
    except (DataFolderInUse, UnwritablePlace, UsersFileError) as err:
        fail(f"fleetdaq: {err}", 2)
    if as_json:
        click.echo(json.dumps(summary, indent=2))
    finish(code)

"""``fleetdaq users``: the dashboard's users (``add``, ``remove``, ``role``, ``list``) in its users
file: one ``name:role:argon2-hash`` line each, written atomically with mode 0600. The running
hub reads the file again when it changes: no restart needed.

A new user's role is ``view`` unless ``--role control`` is given, as for an operator's
certificate (`fleetdaq pki issue --operator`): acting is given, never assumed."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from fleetdaq.cli.common import fail, load_site

MIN_PASSWORD = 8


def _users_file(file: str | None, config: str | None) -> Path:
    from fleetdaq.hub.live.web.users import default_users_file

    if file:
        return Path(file)
    if config:
        configured = load_site(config).hub.dashboard.users_file
        if configured:
            return Path(configured)
    return default_users_file()


def _where(f: click.decorators.FC) -> click.decorators.FC:
    f = click.option(
        "--config", "config", type=click.Path(dir_okay=False),
        help="Site file: use its hub.dashboard.users_file.",
    )(f)  # fmt: skip
    return click.option(
        "--file",
        "file",
        type=click.Path(dir_okay=False),
        help="The users file (default: the site file's hub.dashboard.users_file, else "
        "<state dir>/dashboard-users, e.g. /var/lib/fleetdaq/dashboard-users as root).",
    )(f)


ROLE_HELP = "view: look; control: also act (ack, shelve, outputs, recorder)."


@click.group()
def users() -> None:
    """The dashboard's users: who may log in, and whether they may act (role control: ack,
    shelve, outputs, recorder) or only look (role view)."""


@users.command()
@click.argument("name")
@_where
@click.option(
    "--password-stdin", is_flag=True, help="Read the password from the first line of stdin."
)
@click.option(
    "--role",
    type=click.Choice(["view", "control"]),
    default=None,
    help=f"{ROLE_HELP} [a new user: view; an existing one keeps theirs]",
)
def add(
    name: str, file: str | None, config: str | None, password_stdin: bool, role: str | None
) -> None:
    """Add user NAME (or give them a new password): asked twice, or read from stdin."""
    from fleetdaq.hub.live.web.users import (
        UsersFileError,
        check_name,
        check_role,
        hash_password,
        read_user_lines,
        write_users,
    )

    path = _users_file(file, config)
    try:
        check_name(name)
        lines = read_user_lines(path)
        given = check_role(role) if role is not None else None
    except UsersFileError as err:
        fail(str(err))
    current = {n: u.hashed for n, u in lines.items()}
    roles = {n: u.role for n, u in lines.items()}
    roles[name] = given or (lines[name].role if name in lines else "view")
    if password_stdin:
        password = sys.stdin.readline().rstrip("\r\n")
    else:
        password = click.prompt(
            f"Password for {name}", hide_input=True, confirmation_prompt=True, err=True
        )
    if len(password) < MIN_PASSWORD:
        fail(f"a password of at least {MIN_PASSWORD} characters, please")
    if len(password) > 1024:
        fail("a password of at most 1024 characters, please")
    existed = name in current
    current[name] = hash_password(password)
    try:
        write_users(path, current, roles)
    except UsersFileError as err:
        fail(str(err), 1)
    click.echo(
        f"{'new password for' if existed else 'added'} {name} (role {roles[name]}) in {path}"
    )


@users.command("role")
@click.argument("name")
@click.argument("role", type=click.Choice(["view", "control"]))
@_where
def set_role(name: str, role: str, file: str | None, config: str | None) -> None:
    """Give user NAME the role ROLE (view: look; control: also act). Their open sessions
    follow at their next click."""
    from fleetdaq.hub.live.web.users import UsersFileError, check_role, read_user_lines, write_users

    path = _users_file(file, config)
    try:
        lines = read_user_lines(path)
        if name not in lines:
            fail(f"no user {name!r} in {path}", 1)
        roles = {n: u.role for n, u in lines.items()}
        roles[name] = check_role(role)
        write_users(path, {n: u.hashed for n, u in lines.items()}, roles)
    except UsersFileError as err:
        fail(str(err))
    click.echo(f"{name} has the role {role} in {path}")


@users.command()
@click.argument("name")
@_where
def remove(name: str, file: str | None, config: str | None) -> None:
    """Remove user NAME: their open sessions end at their next request."""
    from fleetdaq.hub.live.web.users import UsersFileError, read_users, write_users

    path = _users_file(file, config)
    try:
        current = read_users(path)
        if name not in current:
            fail(f"no user {name!r} in {path}", 1)
        del current[name]
        write_users(path, current)
    except UsersFileError as err:
        fail(str(err))
    click.echo(f"removed {name} from {path}")


@users.command("list")
@_where
def list_users(file: str | None, config: str | None) -> None:
    """The users, one a line: name and role."""
    from fleetdaq.hub.live.web.users import UsersFileError, read_user_lines

    path = _users_file(file, config)
    try:
        lines = read_user_lines(path)
    except UsersFileError as err:
        fail(str(err))
    names = sorted(lines)
    for n in names:
        click.echo(f"{n} {lines[n].role}")
    if not names:
        click.echo(f"no users in {path}: nobody can log in to the dashboard", err=True)

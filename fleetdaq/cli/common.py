"""What every sub-command shares: one-line failures, loading the site file, signals, logging."""

from __future__ import annotations

import contextlib
import faulthandler
import logging
import os
import signal
import sys
import threading
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, TypeVar

import click

if TYPE_CHECKING:
    from types import FrameType

    import zenoh

    from fleetdaq.certificate_check import Checked
    from fleetdaq.contract.config.site import SiteConfig
    from fleetdaq.hub.config.site import SiteConfig as HubSiteConfig
    from fleetdaq.runtime.security import TlsFiles

F = TypeVar("F", bound=Callable[..., object])

HubAnswer = dict[str, Any]
"""A hub's JSON answer as a command reads it: its values unchecked, read under
`reads_hub_answer` (a field missing or of another type is one line and exit 2)."""


def fail(message: str, code: int = 2) -> NoReturn:
    """Print one line to stderr and exit (2: bad input, 1: it did not work)."""
    click.echo(message, err=True)
    sys.exit(code)


def finish(code: int) -> NoReturn:
    """End a long-running command (hub, edge, demo) once it has stopped cleanly: logs and
    output flushed, then `os._exit`, without the interpreter's finalization.

    Zenoh's native threads (PyO3) may still reach into Python while it finalizes. glibc then
    ends such a thread with a forced unwind, a Rust frame swallows it, and the process aborts
    ("FATAL: exception not rethrown", exit -6) after a clean stop: seen on edges under load
    (cpython#87135, PyO3#4874). By now every file is closed and fsynced and the Zenoh session
    is closed, so there is nothing left for finalization to do."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


DEFAULT_SITE_FILE = Path("/etc/fleetdaq/site.yaml")
"""Where a deployed host has the site file (`ansible/`: fleetdaq_site_file)."""


def _default_site_file() -> str | None:
    return str(DEFAULT_SITE_FILE) if DEFAULT_SITE_FILE.is_file() else None


def site_option(f: F, required: bool = True) -> F:
    """``--config`` of a command that asks the hub: else ``$FLEETDAQ_CONFIG``, else
    /etc/fleetdaq/site.yaml when the host has it (a deployed hub or edge), so `fleetdaq status`
    on a site's machine needs no argument."""
    # Looked at when the command's module loads, i.e. as it runs. No `default` at all when
    # there is none: click (8.5) takes an explicit default=None as a value given.
    found = _default_site_file()
    kwargs: dict[str, Any] = {"default": found} if found else {}  # click.option's **attrs
    return click.option(
        "--config",
        "config",
        envvar="FLEETDAQ_CONFIG",
        required=required,
        type=click.Path(),
        help=f"Site file [else $FLEETDAQ_CONFIG, else {DEFAULT_SITE_FILE} when there].",
        **kwargs,
    )(f)


def hub_options(f: F) -> F:
    """``--config`` (`site_option`) and ``--connect``: what every command asking the hub takes."""
    f = click.option("--connect", multiple=True, help="Hub endpoint(s), overriding the site file.")(
        f
    )
    return site_option(f)


def load_site(path: str | Path) -> HubSiteConfig:
    """The site file validated as the hub does (every section), or one line (file, key path,
    problem) and exit 2."""
    from fleetdaq.contract.errors import ConfigError
    from fleetdaq.hub.config.load import load_config

    try:
        return load_config(path)
    except ConfigError as err:
        fail(str(err))


def load_node_site(path: str | Path) -> SiteConfig:
    """The site file validated as a node reads it (`fleetdaq.contract.config.site`: the hub's
    own sections are checked by the hub), or one line and exit 2."""
    from fleetdaq.contract.config.load import load_config
    from fleetdaq.contract.errors import ConfigError

    try:
        return load_config(path)
    except ConfigError as err:
        fail(str(err))


def check_partition(site: SiteConfig, config: str | Path, partition: str | None) -> None:
    """``--partition NAME``: one of the site's partitions, or one line naming them and exit 2."""
    if partition is not None and partition not in site.hub.partitions:
        named = ", ".join(site.hub.partitions) or "none"
        fail(f"--partition: {config} has no partition {partition!r} in hub.partitions ({named})")


def stop_on_signals(hangup: bool = False) -> threading.Event:
    """An event set by SIGINT or SIGTERM (and SIGHUP with `hangup`: its terminal closed): each
    stops a process cleanly."""
    stop = threading.Event()
    # `kill -USR1 <pid>` prints every thread's stack to stderr: for a process that hangs.
    faulthandler.register(signal.SIGUSR1, all_threads=True)

    def handler(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    if hangup:
        signal.signal(signal.SIGHUP, handler)
    return stop


def stop_with_parent(parent: int, stop: threading.Event) -> None:
    """Stop (as on SIGTERM) when process `parent` ends, however it ends: the kernel sends this
    process SIGTERM when the thread that started it exits (Linux's PR_SET_PDEATHSIG). For the
    demo's edges: a demo killed with SIGKILL (or the OOM killer) leaves no edge running.

    `parent` is the pid the starter gave: if it has already ended (this process has been
    reparented), stop now, because the kernel will never send the signal."""
    import ctypes

    pr_set_pdeathsig = 1
    prctl = getattr(ctypes.CDLL(None, use_errno=True), "prctl", None)  # Linux only
    if prctl is not None and prctl(pr_set_pdeathsig, signal.SIGTERM, 0, 0, 0) != 0:
        err = ctypes.get_errno()
        fail(f"--with-parent: prctl(PR_SET_PDEATHSIG) failed: {os.strerror(err)}", 1)
    if os.getppid() != parent:
        stop.set()


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


class NoAnswer(Exception):
    """No hub answered, or what answered is not a fleetdaq hub: the one line saying why."""


def open_client(
    endpoints: list[str],
    timeout_ms: int = 3000,
    site: SiteConfig | None = None,
    also: str = "",
) -> zenoh.Session:
    """A Zenoh client session to the hub's router, or one line and exit 2 when unreachable
    (`also` ends it). With the site's `security.tls`, the operator's certificate
    (`fleetdaq.runtime.security.operator_tls`)."""
    try:
        return _open(endpoints, timeout_ms, site, also)
    except NoAnswer as err:
        fail(str(err), 2)


def _open(
    endpoints: list[str], timeout_ms: int, site: SiteConfig | None, also: str
) -> zenoh.Session:
    """`open_client`, raising `NoAnswer` instead of exiting."""
    import zenoh

    from fleetdaq.runtime.zenoh_session import client_config

    tls = None
    if site is not None and site.security.tls:
        from fleetdaq.runtime.security import SecretFileError, operator_tls

        try:
            tls = operator_tls(Path(site.security.pki_dir))
        except SecretFileError as err:
            raise NoAnswer(
                f"security.tls is on, but {err} (set FLEETDAQ_CERT and FLEETDAQ_KEY)"
            ) from None
        _warn_if_ending(tls, site)
    try:
        return zenoh.open(client_config(endpoints, timeout_ms=timeout_ms, tls=tls))
    except zenoh.ZError as err:
        hint = _why_tls_failed(tls) if tls is not None else ""
        why = str(err).split(" at /", 1)[0]  # not the Rust source file it was raised in
        raise NoAnswer(
            f"cannot reach the hub at {', '.join(endpoints)}: {why}{hint}{also}"
        ) from None


def _judge_pair(tls: TlsFiles, days_before: float) -> list[Checked]:
    """The operator's certificate and the CA beside it, as `fleetdaq pki check` judges them."""
    import time

    from fleetdaq.certificate_check import judge
    from fleetdaq.pki import operator_again

    now_ns = time.time_ns()
    renew = f"make it again: {operator_again(tls.cert)}"
    return [
        judge("your certificate", tls.cert, renew, tls.ca, now_ns, days_before),
        judge("the site CA", tls.ca, "copy the site's ca.crt here", None, now_ns, days_before),
    ]


def _warn_if_ending(tls: TlsFiles, site: SiteConfig) -> None:
    """One line on stderr when the operator's certificate ends within the days the hub warns
    of its own (certificate_expiring): the command still runs, and nobody is locked out at
    3 a.m. by a date they were never told of."""
    from fleetdaq.certificate_check import CertificateState
    from fleetdaq.runtime.certificate_dates import warn_days

    mine = _judge_pair(tls, warn_days(site))[0]
    if mine.state is CertificateState.EXPIRING:
        click.echo(f"note: your certificate {tls.cert} {mine.message}", err=True)


def _why_tls_failed(tls: TlsFiles) -> str:
    """What the operator's own files say when the hub could not be reached over TLS: a refused
    handshake tells the client nothing, but a certificate that has ended (or not started by this
    clock, or is not from the CA beside it) is what a person can fix."""
    from fleetdaq.certificate_check import GOOD

    for judged in _judge_pair(tls, 0.0):
        if judged.state not in GOOD:
            return f" ({judged.which} {judged.path}: {judged.message})"
    return " (is your certificate from this site's CA?)"


def operator_key(site: SiteConfig, what: str) -> str:
    """The key of the hub's service `what` for this operator: ``.../hub/<what>``, or with
    security on ``.../hub/<what>/by/<name>``, the name in this operator's certificate (the
    router lets a certificate ask only under its own name)."""
    from fleetdaq.contract.keys import SiteKeys

    key = SiteKeys(site.site).hub(what)
    if not site.security.tls:
        return key
    from fleetdaq.pki import operator_name
    from fleetdaq.runtime.security import operator_tls

    return f"{key}/by/{operator_name(operator_tls(Path(site.security.pki_dir)).cert)}"


def hub_request(
    config: str,
    connect: tuple[str, ...],
    what: str,
    body: Mapping[str, object] | None,
    timeout: float = 10.0,
    partition: str | None = None,
) -> HubAnswer:
    """Ask the hub's ``fleetdaq/<site>/hub/<what>`` (a JSON request, a JSON reply); one line and
    exit 2 when no hub answers. With `partition`, through that partition hub's router.
    (`ask_hub` gives the values as `object`, for a command that narrows them itself.)"""
    try:
        return ask_hub(config, connect, what, body, timeout, partition)
    except NoAnswer as err:
        fail(str(err), 2)


def ask_hub(
    config: str,
    connect: tuple[str, ...],
    what: str,
    body: Mapping[str, object] | None,
    timeout: float = 10.0,
    partition: str | None = None,
    name_partitions: bool = True,
) -> dict[str, object]:
    """`hub_request`, raising `NoAnswer` instead of exiting. When the main hub of a partitioned
    site does not answer, the line names its partition hubs (unless not `name_partitions`)."""
    import json

    site = load_site(config)
    check_partition(site, config, partition)
    own = site.hub.partitions[partition].listen if partition is not None else site.hub.listen
    endpoints = list(connect) or list(own)
    # The main hub down: its partition hubs still answer for their own slices.
    also = (
        f"; each partition hub answers for its own slice: --partition "
        f"{' | '.join(site.hub.partitions)}"
        if partition is None and site.hub.partitions and name_partitions
        else ""
    )
    session = _open(endpoints, 3000, site, also)
    payload = json.dumps(body).encode() if body is not None else None
    try:
        try:
            key = operator_key(site, what)
        except ValueError as err:  # SecretFileError, PkiError: which file, and why
            raise NoAnswer(f"security.tls is on, but {err}") from None
        for reply in session.get(key, payload=payload, timeout=timeout):
            if reply.ok is not None:
                try:
                    out = json.loads(reply.ok.payload.to_bytes())
                except ValueError as err:
                    raise NoAnswer(
                        f"the answer on {key} is not JSON ({err}): is that a fleetdaq hub?"
                    ) from None
                if not isinstance(out, dict):
                    raise NoAnswer(
                        f"the answer on {key} is not a JSON object: is that a fleetdaq hub?"
                    )
                return out
    finally:
        session.close()
    why = (
        "is it running, and does security.operators give your certificate this request?"
        if site.security.tls
        else "is it running?"
    )
    raise NoAnswer(f"no hub answered at {', '.join(endpoints)} within {timeout:g} s ({why}){also}")


def reads_hub_answer(f: F) -> F:
    """For a command that prints what a hub answered: an answer it cannot read (a field
    missing or of another type: a hub of another fleetdaq version, or not a fleetdaq hub at
    all) is one line and exit 2, not a traceback."""
    import functools

    @functools.wraps(f)
    def wrapper(*args: object, **kwargs: object) -> object:
        try:
            return f(*args, **kwargs)
        except (KeyError, TypeError, AttributeError, IndexError, ValueError) as err:
            from fleetdaq import __version__

            fail(
                f"the hub's answer is not one this fleetdaq ({__version__}) reads "
                f"({type(err).__name__}: {err}); is the hub running the same version?",
                2,
            )

    return typing.cast(F, wrapper)


def check_tls(config: str | Path, site: SiteConfig, who: str, partition: str | None = None) -> None:
    """With `security.tls` on, the files `who` (``hub``, a node's name, ``operator``) needs
    (the hub: partition hub `partition`'s own pair when given): missing, or a key others may
    read -> one line and exit 2."""
    if not site.security.tls:
        return
    from fleetdaq.runtime.security import SecretFileError, hub_tls, node_tls, operator_tls

    pki = Path(site.security.pki_dir)
    try:
        if who == "hub":
            hub_tls(pki, partition)
        elif who == "operator":
            operator_tls(pki)
        else:
            node_tls(pki, who)
    except SecretFileError as err:
        fail(f"{config}: security.tls is on, but {err}", 2)

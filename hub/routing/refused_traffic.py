"""Traffic the hub's router refuses before any hub service sees it: messages its access control
list drops and TLS handshakes it refuses (read from the router's log,
`fleetdaq.hub.routing.router_log`).
Counted per peer and certificate (ACL) or per reason (TLS), bounded like
`fleetdaq.hub.nodes.refused`; raised
as an event once a minute per peer or reason at most; in the read model, so ``/metrics`` and
the status request show them."""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import TypeVar

from fleetdaq.contract.requester_text import text_problem
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.read_model import (
    REFUSED_ACL,
    REFUSED_ACL_TOTAL,
    REFUSED_TLS,
    REFUSED_TLS_TOTAL,
    ReadModel,
)
from fleetdaq.hub.routing.router_log import (
    AclDenial,
    PeerAccepted,
    RouterLine,
    TlsAccepted,
    TlsRefusal,
    UnknownSubject,
)

_MAX_SLOTS = 256
_MAX_PEERS = 1024
_REPORT_EVERY_S = 60.0
K = TypeVar("K")
V = TypeVar("V")
OTHER_PEERS = ("(other peers)", "")
OTHER_REASONS = "(other reasons)"
UNKNOWN = "unknown"


def peer_host(address: str) -> str:
    """The host of ``ip:port`` (``[::1]:7447`` -> ``[::1]``): a peer's ports change with each
    connection, its host does not, so counts are kept per host."""
    host, sep, _port = address.rpartition(":")
    return host if sep else address


def _shown(text: str, limit: int = 200) -> str:
    """`text` as it may go into an event: a key a peer chose is shown escaped when it breaks
    the rule for requester text (`fleetdaq.contract.requester_text`)."""
    return text if text_problem(text, limit) is None else ascii(text[:limit])


class RefusedTraffic:
    """Counts what the router refused; fed by `fleetdaq.hub.routing.router_log.RouterLogTap` on its
    thread."""

    def __init__(
        self,
        bus: EventBus,
        model: ReadModel,
        hub: str = "hub",
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """`hub`: how events name this hub's router (``hub``, or ``partition hub P``); `clock`:
        monotonic seconds, for the once-a-minute events."""
        self.bus = bus
        self.clock = clock
        self.model = model
        self.hub = hub
        self.acl: dict[tuple[str, str], int] = {}
        self.tls: dict[str, int] = {}
        self.acl_total = 0
        self.tls_total = 0
        self._peers: OrderedDict[str, str] = OrderedDict()  # zid -> ip:port
        self._certificates: OrderedDict[str, str] = OrderedDict()  # ip:port -> CN
        self._no_subject: OrderedDict[str, None] = OrderedDict()  # zids waiting for an address
        self._reported: dict[object, float] = {}
        self._lock = threading.Lock()

    def refused(self, line: RouterLine) -> None:
        """Take one line of the router's log (cheap; an event at most once a minute per slot)."""
        if isinstance(line, TlsAccepted):
            _remember(self._certificates, line.address, line.cn)
        elif isinstance(line, PeerAccepted):
            _remember(self._peers, line.zid, line.address)
            if line.zid in self._no_subject:
                del self._no_subject[line.zid]
                cn = self._certificates.get(line.address, "")
                self._count_acl(
                    line.address, cn, "anything (its certificate is not in the ACL)", ""
                )
        elif isinstance(line, UnknownSubject):
            # zenoh writes this before the line that names the peer's address: counted then
            _remember(self._no_subject, line.zid, None)
        elif isinstance(line, AclDenial):
            address = self._peers.get(line.zid, UNKNOWN)
            cn = line.cn or self._certificates.get(address, "")
            self._count_acl(address, cn, line.what, line.key)
        elif isinstance(line, TlsRefusal):
            self._count_tls(line.reason)

    def _count_acl(self, address: str, cn: str, what: str, key: str) -> None:
        """`what` refused on `key`; `key` "" for a peer whose certificate matches no subject of
        the list (all it sends is dropped, counted once per connection)."""
        now = self.clock()
        with self._lock:
            self.acl_total += 1
            slot = (peer_host(address), cn)
            if slot not in self.acl and len(self.acl) >= _MAX_SLOTS:
                slot = OTHER_PEERS
            n = self.acl[slot] = self.acl.get(slot, 0) + 1
            report = self._due(("acl", slot), now)
        if not report:
            return
        who = f"{address} (certificate {cn or 'unknown'})"
        if key:
            what = (
                f"refused {what} on {_shown(key)} from {who}: its access control list does "
                "not allow it"
            )
        else:
            what = (
                f"refuses everything from {who}: the certificate matches no subject of its "
                "access control list"
            )
        self.bus.emit(
            logging.WARNING,
            "hub",
            "acl_refused",
            f"the {self.hub}'s router {what} ({n} refused from {slot[0]} so far; "
            "once a minute at most)",
            peer=address,
            certificate=cn,
            count=n,
        )

    def _count_tls(self, reason: str) -> None:
        now = self.clock()
        with self._lock:
            self.tls_total += 1
            slot = reason if reason in self.tls or len(self.tls) < _MAX_SLOTS else OTHER_REASONS
            n = self.tls[slot] = self.tls.get(slot, 0) + 1
            report = self._due(("tls", slot), now)
        if report:
            self.bus.emit(
                logging.WARNING,
                "hub",
                "tls_refused",
                f"the {self.hub}'s router refused a TLS handshake: {_shown(reason)} (a client "
                "with a pair from another CA, without one, or not speaking TLS; zenoh does not "
                f"name the peer) ({n} so far; once a minute at most)",
                reason=slot,
                count=n,
            )

    def _due(self, slot: object, now: float) -> bool:
        last = self._reported.get(slot)
        if last is not None and now - last < _REPORT_EVERY_S:
            return False
        self._reported[slot] = now
        return True

    def unavailable(self, why: str) -> None:
        """The router's log cannot be read: say so once, loudly (nothing will be counted)."""
        self.bus.emit(
            logging.ERROR,
            "hub",
            "refused_traffic_uncounted",
            f"the {self.hub}'s router runs, but what it refuses (ACL, TLS) is not counted: {why}",
        )

    def publish(self) -> None:
        """Put the counts into the read model (after each read of the router's log)."""
        with self._lock:
            acl = tuple((p, c, n) for (p, c), n in sorted(self.acl.items()))
            tls = tuple(sorted(self.tls.items()))
            totals = self.acl_total, self.tls_total
        self.model.put(REFUSED_ACL, acl)
        self.model.put(REFUSED_TLS, tls)
        self.model.put(REFUSED_ACL_TOTAL, totals[0])
        self.model.put(REFUSED_TLS_TOTAL, totals[1])


def _remember(table: OrderedDict[K, V], key: K, value: V) -> None:
    table[key] = value
    table.move_to_end(key)
    while len(table) > _MAX_PEERS:
        table.popitem(last=False)

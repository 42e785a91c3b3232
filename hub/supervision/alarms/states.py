"""An alarm's state, as ISA-18.2 / IEC 62682 has it.

    normal ──raised──▶ active_unacked ──acked──▶ active_acked ──cleared──▶ normal
                           │                                                  ▲
                           └──cleared (latched)──▶ returned_unacked ──acked──┘
                           └──cleared (not latched)──▶ normal

An alarm raised again while returned-unacked is active-unacked again. Shelved (with an expiry)
and disabled (out of service) set it aside whatever its condition does; when it comes back it
takes its real state: active-unacked if the condition holds, normal if not. The condition is
tracked all along (`active`). Every change returns a `Change`; nothing here does I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum


class State(StrEnum):
    NORMAL = "normal"
    ACTIVE_UNACKED = "active_unacked"
    ACTIVE_ACKED = "active_acked"
    RETURNED_UNACKED = "returned_unacked"
    SHELVED = "shelved"
    DISABLED = "disabled"


class Transition(StrEnum):
    """What happened to an alarm (the ``alarm_<transition>`` event's tag, the journal's and the
    recording's ``transition``)."""

    RAISED = "raised"
    CLEARED = "cleared"
    ACKED = "acked"
    SHELVED = "shelved"
    UNSHELVED = "unshelved"
    SHELVE_EXPIRED = "shelve_expired"
    DISABLED = "disabled"
    ENABLED = "enabled"


IN_ALARM = {State.ACTIVE_UNACKED, State.ACTIVE_ACKED, State.RETURNED_UNACKED}
UNACKED = {State.ACTIVE_UNACKED, State.RETURNED_UNACKED}


@dataclass(frozen=True, slots=True)
class Change:
    """A transition: what happened, the state it led to, who did it."""

    transition: Transition
    state: State
    time_ns: int
    value: float = math.nan
    user: str = ""
    host: str = ""
    note: str = ""


class Refused(Exception):
    """An operator action that does not apply (ack of a normal alarm, ...): the reason."""


@dataclass(slots=True)
class AlarmStatus:
    """The mutable state of one alarm."""

    latch: bool
    state: State = State.NORMAL
    active: bool = False
    """The condition holds (after its delays), whatever the state says."""
    since_ns: int = 0
    count: int = 0
    value: float = math.nan
    shelved_until_ns: int = 0

    def _to(self, state: State, transition: Transition, t: int, **who: str) -> Change:
        self.state = state
        self.since_ns = t
        return Change(transition, state, t, self.value, **who)

    # --- the condition ----------------------------------------------------------------------

    def condition(self, active: bool, t: int, value: float = math.nan) -> Change | None:
        """The condition became `active` (or not) at acquisition / wall time `t`."""
        if active == self.active:
            return None
        self.active = active
        self.value = value
        if self.state in (State.SHELVED, State.DISABLED):
            return None  # tracked, not announced
        if active:
            if self.state in (State.NORMAL, State.RETURNED_UNACKED):
                self.count += 1
                return self._to(State.ACTIVE_UNACKED, Transition.RAISED, t)
            return None
        if self.state is State.ACTIVE_ACKED:
            return self._to(State.NORMAL, Transition.CLEARED, t)
        if self.state is State.ACTIVE_UNACKED:
            return self._to(
                State.RETURNED_UNACKED if self.latch else State.NORMAL, Transition.CLEARED, t
            )
        return None

    # --- operators ---------------------------------------------------------------------------

    def ack(self, t: int, user: str, host: str, note: str = "") -> Change:
        who = {"user": user, "host": host, "note": note}
        if self.state is State.ACTIVE_UNACKED:
            return self._to(State.ACTIVE_ACKED, Transition.ACKED, t, **who)
        if self.state is State.RETURNED_UNACKED:
            return self._to(State.NORMAL, Transition.ACKED, t, **who)
        if self.state is State.ACTIVE_ACKED:
            raise Refused("already acked")
        raise Refused(f"nothing to ack: it is {self.state.value}")

    def shelve(self, t: int, until_ns: int, user: str, host: str, note: str = "") -> Change:
        if self.state is State.DISABLED:
            raise Refused("it is disabled; enable it first")
        if until_ns <= t:
            raise Refused("a shelve needs an expiry in the future")
        self.shelved_until_ns = until_ns
        return self._to(State.SHELVED, Transition.SHELVED, t, user=user, host=host, note=note)

    def unshelve(self, t: int, user: str = "", host: str = "", note: str = "") -> Change:
        if self.state is not State.SHELVED:
            raise Refused(f"it is not shelved (it is {self.state.value})")
        return self._back(
            t, Transition.UNSHELVED if user else Transition.SHELVE_EXPIRED, user, host, note
        )

    def expire(self, t: int) -> Change | None:
        """The shelve's expiry passed at `t`: back to its real state."""
        if self.state is State.SHELVED and t >= self.shelved_until_ns:
            return self._back(t, Transition.SHELVE_EXPIRED, "", "", "")
        return None

    def disable(self, t: int, user: str, host: str, note: str = "") -> Change:
        if self.state is State.DISABLED:
            raise Refused("already disabled")
        self.shelved_until_ns = 0
        return self._to(State.DISABLED, Transition.DISABLED, t, user=user, host=host, note=note)

    def enable(self, t: int, user: str, host: str, note: str = "") -> Change:
        if self.state is not State.DISABLED:
            raise Refused(f"it is not disabled (it is {self.state.value})")
        return self._back(t, Transition.ENABLED, user, host, note)

    def _back(self, t: int, transition: Transition, user: str, host: str, note: str) -> Change:
        """Out of shelve / service: unacked if the condition holds, normal if not."""
        self.shelved_until_ns = 0
        if self.active:
            self.count += 1
            return self._to(State.ACTIVE_UNACKED, transition, t, user=user, host=host, note=note)
        return self._to(State.NORMAL, transition, t, user=user, host=host, note=note)

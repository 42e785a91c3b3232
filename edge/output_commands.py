"""What the edge answers to one command: decode it, answer a replay as before, check it
(`fleetdaq.edge.command_check`), do it on the output's device, build the `OutputReply`, raise the
event. Called by the output service's worker thread only.

A command id seen before with the same command (a retry, or a replay of captured bytes) is
answered with the reply it got then, marked ``replay``: the original outcome, readback and
times, never applied again and never read back anew. The same id with another command is
refused (not_allowed). Ids are remembered for as long as their command could pass the age
check (`issued_ns` + the effective age limit, never above the site's ceiling
`commands.max_age_s`), and at most `REPLY_MEMORY` of them: an id forgotten is one whose
command is too old by then, so its replay is refused `too_old` and still not applied again.
With the memory full of ids still young enough, a new command is refused (not_allowed, busy)
rather than forget one that could still be replayed. Not remembered: reads (they move
nothing), and refusals before a command could be read (a payload that is not an
OutputCommand, requester text that breaks `fleetdaq.contract.requester_text`, a command on another
output's key).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Protocol

from fleetdaq.contract.cdr import decode, encode
from fleetdaq.contract.errors import DriverError, WireError
from fleetdaq.contract.messages import OutputAction, OutputCommand, OutputReply, RefusalReason
from fleetdaq.contract.requester_text import text_problem
from fleetdaq.edge.command_check import NodeControlState, Refusal, age_limit_s, check_command
from fleetdaq.edge.drivers.pacing import TimeSource
from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.interlocks import Interlocks
from fleetdaq.edge.output_channel import OutputChannel, Pulse

REPLY_MEMORY = 10_000
"""Command ids whose reply is kept at most (each for as long as its command could be applied)."""
TEXT_LIMITS = (("command_id", 128), ("who", 400), ("reason", 500))
"""The command's requester text and its limits (characters): the hub sends user@host as who."""


@dataclass(frozen=True, slots=True)
class _Answered:
    command: OutputCommand
    reply: OutputReply
    until_ns: int
    """After this (edge CLOCK_REALTIME), a replay of the command would be too old."""


class SafeState(Protocol):
    """Where the node's safe state is kept (the output service)."""

    @property
    def safe_state(self) -> bool: ...

    @property
    def safe_reason(self) -> str: ...


class CommandDesk:
    """Answers commands for the outputs in `channels`."""

    def __init__(
        self,
        node: str,
        channels: dict[str, OutputChannel],
        interlocks: Interlocks,
        events: EventPublisher,
        clock: TimeSource,
        state: SafeState,
        max_command_age_s: float,
        memory: int = REPLY_MEMORY,
    ) -> None:
        """`max_command_age_s`: the node's limit under the site's ceiling; `memory`: the most
        command ids remembered for replays."""
        self.node = node
        self.channels = channels
        self.interlocks = interlocks
        self.events = events
        self.clock = clock
        self.state = state
        self.max_command_age_s = max_command_age_s
        self.malformed = 0
        self._malformed_reported = 0
        self.memory = memory
        self._replies: OrderedDict[str, _Answered] = OrderedDict()

    def decide(self, output: str, data: bytes) -> bytes:
        """The reply (encoded) to a query on the key of `output` carrying `data`."""
        try:
            cmd = decode(data, OutputCommand)
        except WireError as err:
            self.malformed += 1
            self._report_malformed(output, str(err))
            return encode(self.reply(None, output, Refusal(RefusalReason.NOT_ALLOWED, f"{err}")))
        if cmd.output != output:
            elsewhere = Refusal(
                RefusalReason.NOT_ALLOWED,
                f"the command names output {cmd.output!r} but came on the key of {output!r}",
            )
            return self._finish(cmd, output, elsewhere, remember=False)
        for field, limit in TEXT_LIMITS:
            why = text_problem(getattr(cmd, field), limit)
            if why is not None:
                # Not echoed anywhere: the text is what could not be recorded.
                self.malformed += 1
                self._report_malformed(output, f"{field} {why}")
                bad = Refusal(RefusalReason.NOT_ALLOWED, f"{field} {why}")
                answered = cmd if field != "command_id" else None
                return encode(self.reply(answered, output, bad))
        now_ns = self.clock.time_ns()
        self._forget(now_ns)
        seen = self._replies.get(cmd.command_id)
        if seen is not None:
            if _same(seen.command, cmd):
                return self._replay(cmd, seen, now_ns)
            reused = Refusal(
                RefusalReason.NOT_ALLOWED,
                f"command id {cmd.command_id!r} was used for another command",
            )
            return self._finish(cmd, output, reused, remember=False)
        if len(self._replies) >= self.memory and cmd.action != OutputAction.READ:
            soonest = min(seen.until_ns for seen in self._replies.values())
            busy = Refusal(
                RefusalReason.NOT_ALLOWED,
                f"busy: {len(self._replies)} commands young enough to be replayed are "
                "remembered, the most this edge keeps (a replay could not be told from a new "
                f"command); try again in {max(0.0, (soonest - now_ns) / 1e9):.1f} s",
            )
            return self._finish(cmd, output, busy, remember=False)
        ch = self.channels.get(cmd.output)
        if ch is None:
            known = ", ".join(self.channels) or "none"
            unknown = Refusal(
                RefusalReason.UNKNOWN_OUTPUT,
                f"no output {cmd.output!r} on {self.node} (outputs: {known})",
            )
            return self._finish(cmd, output, unknown)
        node = NodeControlState(
            self.state.safe_state, self.state.safe_reason, self.max_command_age_s
        )
        view = ch.view(self.interlocks.active_for(ch.name))
        refusal = check_command(cmd, view, node, now_ns, ch.now_s())
        if refusal is None:
            refusal = self._apply(cmd, ch)
        if refusal is None:
            ch.commands += 1
        else:
            ch.refused += 1
        return self._finish(cmd, output, refusal)

    def _replay(self, cmd: OutputCommand, seen: _Answered, now_ns: int) -> bytes:
        """The reply `cmd`'s id got the first time, marked as a replay; a retry stamped anew
        keeps the id remembered for as long as it could itself be applied."""
        until = cmd.issued_ns + int(age_limit_s(cmd, self.max_command_age_s) * 1e9)
        if until > seen.until_ns:
            self._replies[cmd.command_id] = dataclasses.replace(seen, until_ns=until)
        self._replies.move_to_end(cmd.command_id)
        first = seen.reply
        outcome = (
            f"applied, read back {first.readback:g}"
            if first.applied
            else f"refused: {first.refusal}"
        )
        self.events.emit(
            logging.INFO,
            cmd.output,
            "command_retried",
            f"{cmd.command_id}: a replay, answered with its original outcome ({outcome}, "
            f"{(now_ns - first.replied_ns) / 1e9:.3f} s ago); not applied again",
            command_id=cmd.command_id,
            output=cmd.output,
            action=cmd.action,
            applied=str(first.applied).lower(),
        )
        return encode(dataclasses.replace(first, replay=True))

    def _forget(self, now_ns: int) -> None:
        """Forget the ids whose commands are too old to be applied now: from the front (the
        order ids were last seen in), and all through once the memory is full."""
        replies = self._replies
        while replies:
            oldest = next(iter(replies.values()))
            if oldest.until_ns >= now_ns:
                break
            replies.popitem(last=False)
        if len(replies) >= self.memory:
            for key in [k for k, seen in replies.items() if seen.until_ns < now_ns]:
                del replies[key]

    def _apply(self, cmd: OutputCommand, ch: OutputChannel) -> Refusal | None:
        """Do what an allowed command says; a device's refusal is the reply."""
        action = cmd.action
        try:
            if action == OutputAction.READ:
                ch.read_back()
                if ch.cfg.readback == "device" and ch.fault:
                    return Refusal(RefusalReason.DEVICE_ERROR, ch.fault)
            elif action == OutputAction.ARM:
                ch.armed = True
            elif action == OutputAction.DISARM:
                ch.armed = False
            elif action == OutputAction.SET:
                ch.pulse = None
                ch.write(cmd.value)
            elif action == OutputAction.PULSE:
                back_to = ch.pulse.back_to if ch.pulse is not None else ch.value
                ch.pulse = None
                ch.write(cmd.value)
                ch.pulse = Pulse(ch.now_s() + cmd.pulse_s, back_to, cmd.command_id)
        except DriverError as err:
            return Refusal(RefusalReason.DEVICE_ERROR, str(err))
        return None

    def _finish(
        self, cmd: OutputCommand, output: str, refusal: Refusal | None, remember: bool = True
    ) -> bytes:
        reply = self.reply(cmd, output, refusal)
        payload = encode(reply)
        if remember and cmd.action != OutputAction.READ:
            until = cmd.issued_ns + int(age_limit_s(cmd, self.max_command_age_s) * 1e9)
            self._replies[cmd.command_id] = _Answered(cmd, reply, until)
        applied = refusal is None
        level = logging.INFO if applied else logging.WARNING
        if cmd.action == OutputAction.READ:
            level = logging.DEBUG
        what = f"applied, reads back {reply.readback:g}" if applied else f"refused: {reply.refusal}"
        self.events.emit(
            level,
            output,
            "command_applied" if applied else "command_refused",
            f"{cmd.action} {cmd.value:g} from {cmd.sender} {cmd.who} ({cmd.reason}): {what}"
            + ("" if applied else f" ({reply.message})"),
            command_id=cmd.command_id,
            output=output,
            action=cmd.action,
            value=f"{cmd.value:g}",
            sender=cmd.sender,
            who=cmd.who,
            refusal=reply.refusal,
            readback=f"{reply.readback:g}",
        )
        return payload

    def reply(self, cmd: OutputCommand | None, output: str, refusal: Refusal | None) -> OutputReply:
        ch = self.channels.get(output)
        return OutputReply(
            command_id=cmd.command_id if cmd is not None else "",
            output=output,
            action=cmd.action if cmd is not None else "",
            applied=refusal is None,
            refusal=refusal.reason if refusal is not None else "",
            message=refusal.message if refusal is not None else "",
            requested=cmd.value if cmd is not None else math.nan,
            readback=ch.readback if ch is not None else math.nan,
            readback_ns=ch.readback_ns if ch is not None else 0,
            readback_source=ch.source if ch is not None else "",
            armed=ch.armed if ch is not None else False,
            safe_state=self.state.safe_state,
            interlocks=self.interlocks.active_for(output) if ch is not None else (),
            replied_ns=self.clock.time_ns(),
        )

    def _report_malformed(self, output: str, why: str) -> None:
        n = self.malformed
        if n == 1 or n >= self._malformed_reported * 10:
            self._malformed_reported = n
            self.events.emit(
                logging.WARNING,
                "outputs",
                "malformed_command",
                f"refused a payload on out/{output} that is not an OutputCommand this edge "
                f"can apply and record ({why}); {n} so far",
                output=output,
                count=n,
            )


def _same(a: OutputCommand, b: OutputCommand) -> bool:
    """The same command (a retry may be stamped again: its time and max age do not count)."""
    keys = ("output", "action", "value", "pulse_s", "sender", "who", "reason")
    return all(getattr(a, k) == getattr(b, k) for k in keys)

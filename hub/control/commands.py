"""Commands to the nodes' outputs, through the hub: the only way an output is driven.

Operators (``fleetdaq out ...``: a JSON request on ``fleetdaq/<site>/hub/out``) and rules (in
this process) ask `CommandService.send`; it checks the output exists in the site file and
that no hub interlock holds it, sends an `OutputCommand` to the edge's queryable
(``fleetdaq/<site>/<node>/out/<output>``), waits for the `OutputReply` (or times out), and
records the pair as a `CommandRecord` on ``/<node>/commands`` and as an event. A command to a
node the site file does not have is refused here and recorded on ``/hub/commands``: no channel
is ever named by a requester. Sending blocks only the caller's thread: operators' requests run
on a small pool, never on a Zenoh callback.

Every command carries the node's age limit as its `max_age_s` (`SiteConfig.command_age_limit_s`:
never above the site's ceiling `commands.max_age_s`). An operator's text (reason, user, host,
command id, output) is checked first (`fleetdaq.contract.requester_text`): a request that breaks the
rule is answered with the reason and nothing else happens (no command, no record, no event). An
edge's reply marked ``replay`` (a command id it had answered) is recorded as such and is not counted
as applied again."""

from __future__ import annotations

import logging
import math
import threading
import time
import uuid
from collections.abc import Callable

from pydantic import BaseModel

from fleetdaq.contract.cdr import decode, encode
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import (
    COMMAND_RECORD_TYPE,
    CommandRecord,
    OutputCommand,
    OutputReply,
    OutputState,
    RefusalReason,
)
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.read_model import COMMANDS, HubView, JsonObject, ReadModel, to_jsonable
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.recording.session import commands_topic
from fleetdaq.hub.requests import (
    VALUED,
    BadRequest,
    Caller,
    ControlAction,
    ControlRequest,
    OperatorQueryable,
    read_control_request,
    refusal,
)
from fleetdaq.hub.routing.router import Router

log = logging.getLogger("fleetdaq.commands")

HUB_COMMANDS_TOPIC = "/hub/commands"
"""Where commands to nodes the site file does not have are recorded (refused)."""

Blocked = Callable[[str, str], str | None]
"""blocked(node, output): the name of a hub interlock holding that output, or None."""


def refused(cmd: OutputCommand, refusal: RefusalReason, message: str) -> OutputReply:
    return OutputReply(
        command_id=cmd.command_id, output=cmd.output, action=cmd.action, applied=False,
        refusal=refusal, message=message, requested=cmd.value, readback=math.nan,
        readback_ns=0, readback_source="", armed=False, safe_state=False, interlocks=(),
        replied_ns=time.time_ns(),
    )  # fmt: skip


class CommandService:
    name = "commands"

    def __init__(
        self,
        router: Router,
        site: SiteConfig,
        bus: EventBus,
        model: ReadModel,
        recorder: Recorder,
        snapshot: Callable[[], HubView],
        timeout_s: float = 5.0,
        blocked: Blocked | None = None,
    ) -> None:
        """`blocked`: the hub's cross-node interlocks (`fleetdaq.hub.control.rules.Interlocks`);
        None: none."""
        self.router = router
        self.site = site
        self.keys = SiteKeys(site.site)
        self.bus = bus
        self.model = model
        self.recorder = recorder
        self.snapshot = snapshot
        self.timeout_s = timeout_s
        self.blocked: Blocked = blocked or (lambda node, output: None)
        self.sent = 0
        self.applied = 0
        self.refused = 0
        self.timeouts = 0
        self.replayed = 0
        self._lock = threading.Lock()
        # Operators' requests block while the edge is asked: a small pool answers them.
        self.queryable = OperatorQueryable(
            router, self.keys.hub("out"), self.handle, site.security, "commands", workers=4
        )

    # --- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        self.queryable.start()

    def stop(self) -> None:
        self.queryable.stop()

    def failure(self) -> str | None:
        return None

    # --- sending --------------------------------------------------------------------------------

    def outputs(self) -> dict[str, BaseModel]:
        """Every output of the site: ``node/output`` -> its config."""
        out: dict[str, BaseModel] = {}
        for node, cfg in self.site.nodes.items():
            for name, ocfg in getattr(cfg, "outputs", {}).items():
                out[f"{node}/{name}"] = ocfg
        return out

    def send(
        self,
        node: str,
        output: str,
        action: str,
        value: float = math.nan,
        pulse_s: float = 0.0,
        sender: str = "operator",
        who: str = "",
        reason: str = "",
        command_id: str | None = None,
        unblocked: bool = False,
    ) -> tuple[OutputCommand, OutputReply]:
        """Command one output and wait for its reply (at most `timeout_s`). Never raises for
        what the edge or the network does: a refusal or a timeout is in the reply.
        `unblocked`: an interlock's own command (putting its outputs safe) passes it."""
        cmd = OutputCommand(
            command_id=command_id or uuid.uuid4().hex,
            output=output,
            action=action,
            value=float(value),
            pulse_s=float(pulse_s),
            sender=sender,
            who=who,
            reason=reason,
            issued_ns=time.time_ns(),
            max_age_s=self.age_limit_s(node),
        )
        sent_ns = time.time_ns()
        if f"{node}/{output}" not in self.outputs():
            reply = refused(
                cmd, RefusalReason.UNKNOWN_OUTPUT, f"the site file has no output {node}/{output}"
            )
        elif (
            action in VALUED and not unblocked and (lock := self.blocked(node, output)) is not None
        ):
            reply = refused(cmd, RefusalReason.INTERLOCK, f"interlock {lock} active")
        else:
            reply = self._ask(node, cmd)
        self._record(node, cmd, reply, sent_ns)
        return cmd, reply

    def age_limit_s(self, node: str) -> float:
        """The `max_age_s` the hub stamps on a command to `node` (the site's ceiling for a
        node it does not know: such a command is never sent)."""
        if node in self.site.nodes:
            return self.site.command_age_limit_s(node)
        return self.site.commands.max_age_s

    def send_unblocked(
        self,
        node: str,
        output: str,
        action: str,
        value: float,
        pulse_s: float,
        sender: str,
        who: str,
        reason: str,
    ) -> tuple[OutputCommand, OutputReply]:
        return self.send(node, output, action, value, pulse_s, sender, who, reason, None, True)

    def _ask(self, node: str, cmd: OutputCommand) -> OutputReply:
        key = self.keys.out(node, cmd.output)
        try:
            replies = self.router.session.get(key, payload=encode(cmd), timeout=self.timeout_s)
            for r in replies:
                if r.ok is None:
                    continue
                try:
                    reply = decode(r.ok.payload.to_bytes(), OutputReply)
                except WireError as err:
                    return refused(
                        cmd, RefusalReason.TIMEOUT, f"{node} answered with something else: {err}"
                    )
                if reply.command_id != cmd.command_id:
                    return refused(cmd, RefusalReason.TIMEOUT, f"{node} answered another command")
                return reply
        except Exception as err:  # the network, not the command: a timeout for the caller
            log.warning("command to %s/%s: %s", node, cmd.output, err)
            return refused(cmd, RefusalReason.TIMEOUT, f"could not ask {node}: {err}")
        return refused(
            cmd, RefusalReason.TIMEOUT, f"{node} did not answer within {self.timeout_s:g} s"
        )

    def _record(self, node: str, cmd: OutputCommand, reply: OutputReply, sent_ns: int) -> None:
        now = time.time_ns()
        with self._lock:
            self.sent += 1
            if reply.replay:
                self.replayed += 1
            elif reply.applied:
                self.applied += 1
            else:
                self.refused += 1
                self.timeouts += reply.refusal == RefusalReason.TIMEOUT
        record = CommandRecord(cmd, reply, node, sent_ns, now)
        topic = commands_topic(node) if node in self.site.nodes else HUB_COMMANDS_TOPIC
        self.recorder.record(topic, encode(record), sent_ns, now, COMMAND_RECORD_TYPE)
        what = f"{cmd.action} {cmd.value:g}" if cmd.action in VALUED else cmd.action
        by = f"{cmd.sender} {cmd.who}".strip()
        tag = "command_applied" if reply.applied else "command_refused"
        if reply.replay:
            tag = "command_replayed"
            first = time.strftime("%H:%M:%S", time.gmtime(reply.replied_ns / 1e9))
            outcome = (
                f"applied, readback {reply.readback:g}"
                if reply.applied
                else f"refused: {reply.refusal}: {reply.message}"
            )
            line = (
                f"{node}/{cmd.output}: {what} is a replay of command {cmd.command_id}, answered "
                f"with its original outcome ({outcome}, at {first} UTC); not applied again "
                f"— by {by}"
            )
        elif reply.applied:
            readback = (
                ""
                if math.isnan(reply.readback)
                else f", readback {reply.readback:g} ({reply.readback_source})"
            )
            line = f"{node}/{cmd.output}: {what} applied{readback} — by {by}"
        else:
            line = (
                f"{node}/{cmd.output}: {what} refused: {reply.refusal}: {reply.message} — by {by}"
            )
        if cmd.reason:
            line += f"; reason: {cmd.reason}"
        self.bus.emit(
            logging.INFO if reply.applied else logging.WARNING,
            "commands",
            tag,
            line,
            command_id=cmd.command_id,
            node=node,
            output=cmd.output,
            action=cmd.action,
            value=cmd.value,
            sender=cmd.sender,
            who=cmd.who,
            refusal=reply.refusal,
            replay=reply.replay,
        )
        self.model.put(
            COMMANDS,
            {"sent": self.sent, "applied": self.applied, "refused": self.refused,
             "timeouts": self.timeouts, "replayed": self.replayed},
        )  # fmt: skip

    # --- operators' requests ----------------------------------------------------------------

    def handle(self, raw: bytes, caller: Caller | None = None) -> JsonObject:
        """One operator request on ``hub/out`` (JSON) -> its answer (JSON-ready): parsed
        (`read_control_request`), then `act`. With `caller` (security on), its name is the user
        recorded, and only the control role may command."""
        try:
            request = read_control_request(raw)
            if caller is not None:
                request = request.by(caller.name)
                why = refusal(caller, request.action, (ControlAction.LIST,))
                if why:
                    raise BadRequest(why)
        except ValueError as err:
            return {"ok": False, "error": str(err)}
        return self.act(request)

    def act(self, request: ControlRequest) -> JsonObject:
        """An operator's parsed request -> its answer (JSON-ready): the outputs' list, or the
        command sent and its reply. Blocks while the edge is asked: run it on a worker thread.
        The dashboard calls this with the request it parsed (the same parser)."""
        if request.action is ControlAction.LIST:
            return {"ok": True, "error": "", "outputs": self.listing()}
        cmd, reply = self.send(
            request.node,
            request.output_name,
            request.action,
            request.value,
            request.pulse_s,
            "operator",
            f"{request.user}@{request.host}",
            request.reason,
            request.command_id,
        )
        return {"ok": reply.applied, "error": "", "command": to_jsonable(cmd),
                "reply": to_jsonable(reply)}  # fmt: skip

    def listing(self) -> list[JsonObject]:
        """Every output: its config, and what its node last said about it (health)."""
        view = self.snapshot()
        states: dict[str, OutputState] = {}
        for n in view.nodes:
            if n.health is not None:
                for o in n.health.outputs:
                    states[f"{n.node}/{o.name}"] = o
        rows: list[JsonObject] = []
        for ref, cfg in sorted(self.outputs().items()):
            node, output = ref.split("/", 1)
            state = states.get(ref)
            rows.append(
                {
                    "output": ref,
                    "config": to_jsonable(cfg.model_dump(mode="json")),
                    "state": to_jsonable(state) if state is not None else None,
                    "alive": any(n.node == node and n.alive for n in view.nodes),
                    "interlock": self.blocked(node, output),
                }
            )
        return rows

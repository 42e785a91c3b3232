"""A test double of the HUB for the edge's outputs, as its own OS process: a Zenoh router on
loopback (edges connect to it as to the hub's), a `HubHeartbeat` at 1 Hz that can be switched
off, `OutputCommand` queries with the replies they get, and the node's events.

It is driven over stdin/stdout, one JSON object a line (`HubDouble` below starts it and talks
to it). It is not a mock of the unit under test: the edge it talks to is the real agent in its
own process, over real Zenoh.

``python -m tests.hub_double --port P --site S --node N [--no-beat] [--beat-file F]``

Requests: ``{"op": "cmd", ...OutputCommand fields..., "key": output (default: "output"),
"raw": hex payload instead of a command}`` -> ``{"replies": [...], "errors": [...]}``;
``{"op": "beat", "on": bool}``; ``{"op": "junk_beat"}``; ``{"op": "events"}`` ->
``{"events": [...]}``; ``{"op": "health"}`` -> the node's last health outputs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import queue
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent


def _serve(args: argparse.Namespace) -> None:
    import zenoh

    from fleetdaq import __version__
    from fleetdaq.contract.cdr import decode, encode
    from fleetdaq.contract.errors import WireError
    from fleetdaq.contract.keys import EVENTS_STREAM, SiteKeys
    from fleetdaq.contract.messages import (
        Event,
        HubHeartbeat,
        NodeHealth,
        OutputCommand,
        OutputReply,
    )
    from fleetdaq.contract.wire import decode_event_mark, encode_mark
    from fleetdaq.runtime.zenoh_session import router_config

    keys = SiteKeys(args.site)
    session: Any = zenoh.open(router_config([f"tcp/127.0.0.1:{args.port}"]))
    beating = threading.Event()
    if args.beat:
        beating.set()
    lock = threading.Lock()
    events: list[dict[str, Any]] = []
    health: dict[str, Any] = {}

    taken: dict[int, int] = {}  # a spool's epoch -> the next sequence this double takes

    def on_event(sample: Any) -> None:
        try:
            ev = decode(sample.payload.to_bytes(), Event)
        except WireError:
            return
        att = sample.attachment
        mark = decode_event_mark(att.to_bytes()) if att is not None else None
        with lock:
            if mark is not None:
                # As the hub does: each spooled event once, in order, acked once taken (a
                # replay of what an earlier double took, or of what is ahead of a hole, is not).
                seq, floor, epoch = mark
                if seq != taken.get(epoch, floor):
                    return
                taken[epoch] = seq + 1
                session.put(keys.ack(args.node, EVENTS_STREAM), encode_mark(seq, epoch))
            events.append(
                {
                    "time_ns": ev.time_ns,
                    "level": ev.level,
                    "source": ev.source,
                    "tag": ev.tag,
                    "message": ev.message,
                    "fields": {kv.key: kv.value for kv in ev.fields},
                }
            )

    def on_health(sample: Any) -> None:
        try:
            h = decode(sample.payload.to_bytes(), NodeHealth)
        except WireError:
            return
        with lock:
            health["outputs"] = [dataclasses.asdict(o) for o in h.outputs]

    subs = [
        session.declare_subscriber(keys.events(args.node), on_event),
        session.declare_subscriber(keys.health(args.node), on_health),
    ]
    pub = session.declare_publisher(keys.hub("heartbeat"))
    stop = threading.Event()

    def beat() -> None:
        seq = 0
        while not stop.wait(args.period):
            if not beating.is_set():
                continue
            seq += 1
            now = time.time_ns()
            pub.put(encode(HubHeartbeat(now, __version__, "double", seq)))
            if args.beat_file:
                tmp = Path(args.beat_file + ".tmp")
                tmp.write_text(str(now))
                os.replace(tmp, args.beat_file)

    beater = threading.Thread(target=beat, daemon=True)
    beater.start()

    def command(req: dict[str, Any]) -> dict[str, Any]:
        if "raw" in req:
            payload = bytes.fromhex(req["raw"])
        else:
            cmd = OutputCommand(
                command_id=req.get("command_id") or uuid.uuid4().hex,
                output=req["output"],
                action=req.get("action", "set"),
                value=float(req.get("value", 0.0)),
                pulse_s=float(req.get("pulse_s", 0.0)),
                sender=req.get("sender", "operator"),
                who=req.get("who", "test@double"),
                reason=req.get("reason", "test"),
                issued_ns=int(req.get("issued_ns") or time.time_ns()),
                max_age_s=float(req.get("max_age_s", 0.0)),
            )
            payload = encode(cmd)
        key = keys.out(args.node, req.get("key") or req["output"])
        replies: list[dict[str, Any]] = []
        errors: list[str] = []
        for reply in session.get(key, payload=payload, timeout=float(req.get("timeout", 5.0))):
            if reply.ok is None:
                errors.append(str(reply.err.payload.to_bytes()))
                continue
            try:
                r = decode(reply.ok.payload.to_bytes(), OutputReply)
            except WireError as err:
                errors.append(f"undecodable reply: {err}")
                continue
            replies.append(dataclasses.asdict(r) | {"key": str(reply.ok.key_expr)})
        return {"replies": replies, "errors": errors}

    print(json.dumps({"ready": True}), flush=True)
    try:
        for line in sys.stdin:
            req = json.loads(line)
            op = req["op"]
            if op == "cmd":
                out = command(req)
            elif op == "beat":
                if req["on"]:
                    beating.set()
                else:
                    beating.clear()
                out = {"ok": True}
            elif op == "junk_beat":
                pub.put(bytes.fromhex(req.get("raw", "00010000ffffffff")))
                out = {"ok": True}
            elif op == "events":
                with lock:
                    out = {"events": list(events)}
            elif op == "health":
                with lock:
                    out = dict(health)
            else:
                break
            print(json.dumps(out, default=_json_float), flush=True)
    finally:
        stop.set()
        beater.join(5)
        for sub in subs:
            sub.undeclare()
        pub.undeclare()
        session.close()


def _json_float(value: object) -> object:
    return str(value)


class HubDouble:
    """Starts the double in its own process and talks to it (a context manager)."""

    def __init__(
        self, port: int, site: str, node: str, beat: bool = True, beat_file: Path | None = None
    ) -> None:
        args = [sys.executable, "-m", "tests.hub_double", "--port", str(port)]
        args += ["--site", site, "--node", node]
        if not beat:
            args.append("--no-beat")
        if beat_file is not None:
            args += ["--beat-file", str(beat_file)]
        self.popen = subprocess.Popen(
            args,
            cwd=REPO,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        self._lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        ready = self._next(30.0)
        assert ready.get("ready"), ready

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self._lines.put(line)

    def _next(self, timeout: float) -> dict[str, Any]:
        try:
            line = self._lines.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"the hub double did not answer within {timeout} s") from None
        out: dict[str, Any] = json.loads(line)
        return out

    def ask(self, op: str, timeout: float = 30.0, **req: Any) -> dict[str, Any]:
        assert self.popen.stdin is not None
        self.popen.stdin.write(json.dumps({"op": op, **req}) + "\n")
        self.popen.stdin.flush()
        return self._next(timeout)

    def command(self, output: str, action: str = "set", **fields: Any) -> dict[str, Any]:
        """Send one command; return its one reply (fails if there is not exactly one)."""
        got = self.ask("cmd", output=output, action=action, **fields)
        assert len(got["replies"]) == 1, got
        reply: dict[str, Any] = got["replies"][0]
        return reply

    def events(self, tag: str | None = None) -> list[dict[str, Any]]:
        evs: list[dict[str, Any]] = self.ask("events")["events"]
        return [e for e in evs if tag is None or e["tag"] == tag]

    def kill(self) -> None:
        """SIGKILL: the hub dies without a word (its router with it)."""
        if self.popen.poll() is None:
            self.popen.kill()
        self.popen.wait(10)

    def close(self) -> None:
        if self.popen.poll() is None:
            try:
                assert self.popen.stdin is not None
                self.popen.stdin.write(json.dumps({"op": "quit"}) + "\n")
                self.popen.stdin.flush()
                self.popen.wait(10)
            except (OSError, subprocess.TimeoutExpired):
                self.popen.kill()
                self.popen.wait(10)

    def __enter__(self) -> HubDouble:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--site", required=True)
    ap.add_argument("--node", required=True)
    ap.add_argument("--no-beat", dest="beat", action="store_false")
    ap.add_argument("--beat-file")
    ap.add_argument("--period", type=float, default=1.0)
    _serve(ap.parse_args())


if __name__ == "__main__":
    main()

"""A hostile peer on a site's network, as its own process: captures real traffic, then throws
mutated copies and junk at the hub, bounded in count and time.

``python -m tests.hostile_sender --port P --site S --node N --stream T --ghost G --seconds 15``

- on the real stream's key: only copies the hub must refuse (truncated, lying lengths, junk,
  bit flips that break the batch) and exact replays (duplicates): no forgery of a valid new
  sequence, which only the security layer can stop;
- on the ghost node (in the site file, no edge running): anything, including bit-flipped
  batches that decode, batches from the year 1734 and a negative time, events with
  out-of-range times, floods past its share of the receive queue;
- on health, events and hub keys: bit flips, truncations, lying lengths, junk;
- on keys the site file does not define: a flood;
- liveliness tokens that come and go.

Prints one JSON line with what it sent.
"""

from __future__ import annotations

import argparse
import json
import random
import struct
import threading
import time
from typing import Any

import numpy as np
import zenoh

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import make_event
from fleetdaq.contract.wire import BatchEncoder, encode_u64, read_header
from fleetdaq.ptp.quality import UNSYNCED
from fleetdaq.runtime.zenoh_session import client_config


def flip(buf: bytes, rng: random.Random, n: int) -> bytes:
    b = bytearray(buf)
    for _ in range(n):
        i = rng.randrange(len(b))
        b[i] ^= 1 << rng.randrange(8)
    return bytes(b)


def lie(buf: bytes, rng: random.Random) -> bytes:
    """A length field somewhere that claims far more than there is."""
    b = bytearray(buf)
    pos = 4 + 4 * rng.randrange(max(1, (len(b) - 8) // 4))
    b[pos : pos + 4] = rng.choice([0x7FFFFFFF, 0xFFFFFFFF, 2**31 + 5]).to_bytes(4, "little")
    return bytes(b)


def mutants(real: list[bytes], rng: random.Random) -> bytes:
    base = rng.choice(real)
    kind = rng.randrange(5)
    if kind == 0:
        return flip(base, rng, rng.randint(1, 8))
    if kind == 1:
        return base[: rng.randrange(len(base))]
    if kind == 2:
        return lie(base, rng)
    if kind == 3:
        return rng.randbytes(rng.randrange(0, 2000))
    return base + rng.randbytes(rng.randrange(1, 64))  # trailing junk


def refused_by_hub(payload: bytes, node: str, stream: str) -> bool:
    try:
        h = read_header(payload)
    except WireError:
        return True
    return (h.node, h.stream) != (node, stream)


def capture(session: Any, keys: SiteKeys, node: str, seconds: float) -> dict[str, list[bytes]]:
    got: dict[str, list[bytes]] = {"data": [], "health": [], "events": []}
    lock = threading.Lock()

    def keep(kind: str) -> Any:
        def cb(sample: Any) -> None:
            with lock:
                if len(got[kind]) < 200:
                    got[kind].append(sample.payload.to_bytes())

        return cb

    subs = [
        session.declare_subscriber(keys.all_data, keep("data")),
        session.declare_subscriber(keys.health(node), keep("health")),
        session.declare_subscriber(keys.events(node), keep("events")),
    ]
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not (got["data"] and got["health"]):
        time.sleep(0.1)
    time.sleep(min(1.0, max(0.0, deadline - time.monotonic())))
    for s in subs:
        s.undeclare()
    return got


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--site", required=True)
    ap.add_argument("--node", required=True)
    ap.add_argument("--stream", required=True)
    ap.add_argument("--ghost", required=True)
    ap.add_argument("--ghost-stream", required=True)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    keys = SiteKeys(args.site)
    session: Any = zenoh.open(client_config([f"tcp/127.0.0.1:{args.port}"]))
    sent: dict[str, int] = {}

    def put(key: str, payload: bytes, what: str, **kw: Any) -> None:
        session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK, **kw)
        sent[what] = sent.get(what, 0) + 1

    try:
        real = capture(session, keys, args.node, 20.0)
        assert real["data"], "no real traffic to mutate"
        real_events = real["events"] or [
            encode(make_event(time.time_ns(), args.node, 20, "x", "y", "z"))
        ]
        real_health = real["health"]
        gh = BatchEncoder(args.ghost, args.ghost_stream, ("a",), ("V",))
        ghost_real = [
            bytes(gh.encode(s, time.time_ns(), 1e6, np.zeros((50, 1)), UNSYNCED)) for s in range(20)
        ]
        tokens: list[Any] = []
        deadline = time.monotonic() + args.seconds
        i = 0
        while time.monotonic() < deadline and i < 60_000:
            i += 1
            r = i % 13
            if r == 0:  # the real stream: only what the hub must refuse, or a duplicate
                while True:
                    m = mutants(real["data"], rng)
                    if refused_by_hub(m, args.node, args.stream) or m in real["data"]:
                        break
                put(keys.data(args.node, args.stream), m, "real_stream", attachment=encode_u64(0))
            elif r == 1:  # an exact replay: a duplicate
                put(keys.data(args.node, args.stream), rng.choice(real["data"]), "duplicates")
            elif r == 2:  # the ghost stream: anything, including batches that decode
                put(keys.data(args.ghost, args.ghost_stream), mutants(ghost_real, rng), "ghost")
            elif r == 3:  # a ghost batch from the year 1734 / a negative time, well-formed
                t = rng.choice([-7_500_000_000_000_000_000, -1, 2**62])
                seq = 1_000 + i
                put(
                    keys.data(args.ghost, args.ghost_stream),
                    bytes(gh.encode(seq, t, 1e6, np.zeros((50, 1)), UNSYNCED)),
                    "ghost_bad_time",
                )
            elif r == 4:
                if real_health:
                    put(keys.health(args.node), mutants(real_health, rng), "health")
                put(keys.health(args.ghost), rng.randbytes(rng.randrange(4000)), "health")
            elif r == 5:
                put(keys.events(args.node), mutants(real_events, rng), "events")
                e = make_event(rng.choice([-1, -(2**62), 0]), args.ghost, 40, "x", "t", "1734")
                put(keys.events(args.ghost), encode(e), "events_bad_time")
            elif r == 6:
                for what in ("heartbeat", "status", "anything/at/all"):
                    put(keys.hub(what), rng.randbytes(rng.randrange(200)), "hub_keys")
            elif r == 7:  # keys the site file does not define: a burst
                for _ in range(20):
                    node = rng.choice(["evil", "wec2", "x" * 60])
                    put(keys.data(node, f"s{rng.randrange(50)}"), rng.randbytes(300), "unknown")
                    put(keys.data(args.node, "nope"), rng.randbytes(300), "unknown")
                put(keys.health("evil"), b"\x00\x01\x00\x00" + b"[" * 5000, "unknown")
            elif r == 8:  # liveliness tokens that come and go
                if tokens and rng.random() < 0.5:
                    tokens.pop().undeclare()
                else:
                    who = rng.choice(["evil", args.ghost, "x-" + str(rng.randrange(100))])
                    tokens.append(session.liveliness().declare_token(keys.alive(who)))
                sent["tokens"] = sent.get("tokens", 0) + 1
            elif r == 9 and sent.get("ghost_flood", 0) < 200:  # big valid batches, a burst
                big = bytes(
                    gh.encode(5000 + i, time.time_ns(), 1e6, np.ones((20_000, 1)), UNSYNCED)
                )
                put(keys.data(args.ghost, args.ghost_stream), big, "ghost_flood")
            elif r == 10:  # a payload whose first bytes claim CDR but a length lies hugely
                p = b"\x00\x01\x00\x00" + struct.pack("<I", 0xFFFFFFF0) + b"\x00" * 8
                put(keys.data(args.node, args.stream), p, "real_stream")
                put(keys.events(args.node), p, "events")
            elif r == 11:  # a real batch whose floor says everything below 2^40 is gone
                put(
                    keys.data(args.node, args.stream),
                    rng.choice(real["data"]),
                    "lying_floor",
                    attachment=encode_u64(2**40),
                )
            else:
                time.sleep(0.001)
        for t in tokens:
            t.undeclare()
    finally:
        session.close()
    print(json.dumps(sent))


if __name__ == "__main__":
    main()

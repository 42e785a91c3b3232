"""One stream of an edge: acquire, stamp, encode, spool, publish — and replay what the hub has
not acked.

Each stream runs in its own thread (blocking hardware calls never share a loop): read a block
from the driver, apply scale/offset and validity in numpy, stamp it from the device-time fit,
encode, append it to the spool and publish it. A second thread replays unacked batches.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import zenoh

from fleetdaq.contract.config.node import SpoolConfig, StreamConfig
from fleetdaq.contract.errors import DriverError
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.wire import BatchEncoder, encode_mark
from fleetdaq.edge.device_time import DeviceTimeFit, Restart
from fleetdaq.edge.drivers.base import Driver
from fleetdaq.edge.drivers.table import create_driver
from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.spool import StreamSpool
from fleetdaq.edge.time_sync import NoTimeSyncMonitor, TimeSyncMonitor
from fleetdaq.runtime.systemd import Beat
from fleetdaq.runtime.threads import NamedThread
from fleetdaq.runtime.zenoh_session import has_subscribers

log = logging.getLogger("fleetdaq.edge")


@dataclass(slots=True)
class StreamCounters:
    batches: int = 0
    scans: int = 0
    invalid_samples: int = 0
    late_polls: int = 0
    read_errors: int = 0
    next_sequence: int = 0
    replayed: int = 0


OPEN_QUIET_S = 30.0
"""How long opening a device may legitimately keep the loop quiet (the watchdog's view)."""


class StreamLoop:
    """Acquires one stream in its own thread until stopped, and replays from its spool.

    Every batch is appended to the spool before it is published; the hub's acks free the
    spool. A second thread replays unacked batches (rate-limited, oldest first) whenever the
    oldest unacked batch is older than `replay_after_s` and the hub is listening.
    """

    def __init__(
        self,
        site: str,
        node: str,
        name: str,
        cfg: StreamConfig,
        session: zenoh.Session | None,
        events: EventPublisher,
        spool: StreamSpool,
        spool_cfg: SpoolConfig,
        driver: Driver | None = None,
    ) -> None:
        self.name = name
        self.cfg = cfg
        self.events = events
        self.spool = spool
        self.spool_cfg = spool_cfg
        self.driver = driver or create_driver(cfg)
        names = tuple(ch.name for ch in cfg.channels)
        units = tuple(ch.unit for ch in cfg.channels)
        self.encoder = BatchEncoder(node, name, names, units, cfg.sample_format)
        self.channel_index = {ch.name: i for i, ch in enumerate(cfg.channels)}
        self.latest: npt.NDArray[np.float64] | None = None
        """The newest scan in engineering units (what displays show)."""
        self.batch_hooks: list[Callable[[npt.NDArray[np.float64]], None]] = []
        """Called with every batch's (scans, channels) engineering values, NaN where invalid,
        on this stream's thread before the batch is spooled: the edge interlocks. The array is
        reused for the next batch: a hook copies what it keeps."""
        self._hook_failed = False
        self.scale = np.array([ch.scale for ch in cfg.channels])
        self.offset = np.array([ch.offset for ch in cfg.channels])
        self._tiled_scale: npt.NDArray[np.float64] = np.empty(0)
        self._tiled_offset: npt.NDArray[np.float64] = np.empty(0)
        self._scratch: npt.NDArray[np.float64] = np.empty(0)
        self.time_fit = DeviceTimeFit(cfg.rate_hz)
        self.counters = StreamCounters(next_sequence=spool.next_sequence)
        self.time_sync: TimeSyncMonitor = NoTimeSyncMonitor()
        self._key = SiteKeys(site).data(node, name)
        self._pub: zenoh.Publisher | None = None
        self._replay_pub: zenoh.Publisher | None = None
        if session is not None:
            self.attach(session)
        self.subscriber_timeout_s = 3.0
        self.hub_unreachable = threading.Event()
        """Set by the agent when its first attempt to reach the hub failed."""
        self.beat = Beat(f"acquisition of {name}")
        """Shows the loop is alive: the agent hands it to systemd's watchdog
        (`fleetdaq.runtime.systemd`)."""
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._run, name=f"stream-{name}", daemon=True)
        self._replayer = NamedThread(target=self._replay, name=f"replay-{name}", daemon=True)
        self._report_recovery()

    def _report_recovery(self) -> None:
        rec = self.spool.recovery
        if rec.clean or rec.last_seq is None:
            return
        when = rec.last_time_ns or 0
        self.events.emit(
            logging.WARNING,
            self.name,
            "unclean_stop",
            f"the last run stopped without closing its spool (crash, kill or power loss) after "
            f"sequence {rec.last_seq} (acquired {when / 1e9:.3f} s UTC); scans between then and "
            f"this start were never acquired; {rec.torn_bytes} bytes of a torn record cut; "
            f"sequence numbers continue at {self.counters.next_sequence}",
        )

    def attach(self, session: zenoh.Session) -> None:
        """Publish on `session` from now on. Until then batches only go to the spool."""
        # Live batches never block the acquisition thread: under congestion Zenoh drops the
        # put, and the batch, already in the spool, is replayed once the hub has not acked it.
        # Blocking here would stall the device read and overflow the device's buffer instead.
        self._replay_pub = session.declare_publisher(
            self._key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
            priority=zenoh.Priority.DATA_LOW,  # Zenoh sends live data ahead of replays
        )
        self._pub = session.declare_publisher(
            self._key,
            congestion_control=zenoh.CongestionControl.DROP,
            reliability=zenoh.Reliability.RELIABLE,
            priority=zenoh.Priority.DATA_HIGH,
        )

    def _hub_listens(self) -> bool:
        pub = self._pub
        return pub is not None and has_subscribers(pub)

    def start(self) -> None:
        self._thread.start()
        self._replayer.start()

    def wait_for_subscriber(self, timeout: float) -> bool:
        """Wait until the hub's subscription reaches this publisher (bounded).

        A put before that goes nowhere (the spool keeps it for replay, but a run that starts
        with the hub up should not need one). After `timeout` the stream starts anyway.
        """
        deadline = time.monotonic() + timeout
        while not self._hub_listens():
            if self.hub_unreachable.is_set():
                return False  # the first connection attempt failed: acquire into the spool now
            if time.monotonic() >= deadline:
                self.events.emit(
                    logging.WARNING,
                    self.name,
                    "no_hub",
                    f"no hub subscribed after {timeout:g} s; acquiring anyway into the spool",
                )
                return False
            if self._stop.wait(0.02):
                return False
        return True

    def _run(self) -> None:
        backoff = 0.5
        beat = self.beat
        beat.quiet(self.subscriber_timeout_s + OPEN_QUIET_S)
        self.wait_for_subscriber(self.subscriber_timeout_s)
        while not self._stop.is_set():
            try:
                beat.quiet(OPEN_QUIET_S)  # opening a device may take its time (LJM's timeout)
                self.driver.open()
                backoff = 0.5
                self._acquire()
            except InterruptedError:
                break
            except (DriverError, OSError) as err:
                self.counters.read_errors += 1
                self.events.emit(
                    logging.ERROR,
                    self.name,
                    "driver_error",
                    f"driver failed, retrying in {backoff:g} s: {err}",
                )
                with_close(self.driver)
                beat.quiet(backoff + OPEN_QUIET_S)
                if self._stop.wait(backoff):
                    break
                backoff = min(backoff * 2, 30.0)

    def _acquire(self) -> None:
        index = 0  # scans acquired since this open; sequence numbers continue across reopen
        c = self.counters
        beat = self.beat.beat
        while not self._stop.is_set():
            beat()
            block = self.driver.read()
            scans = block.raw.shape[0]
            values = self._engineering(block.raw)
            if block.status is not None:
                bad = block.status != 0
                values[bad] = np.nan
                c.invalid_samples += int(bad.sum())
            # Slots a polled device was not polled in (a late host): no scans, time moves on.
            c.late_polls += block.late_polls
            index += block.late_polls
            for hook in self.batch_hooks:
                self._run_hook(hook, values)
            self.latest = values[-1].copy()  # `values` is reused by the next batch
            for ev in block.events:
                self.events.emit(ev.level, self.name, ev.tag, ev.message, **dict(ev.fields))
            self.time_fit.observe(index + scans - 1, block.host_ns, block.device_ns)
            t0, period = self.time_fit.stamp(index, scans)
            seq = c.next_sequence
            if (restart := self.time_fit.restarted) is not None:
                self._time_restarted(restart, seq)
            payload = self.encoder.encode(
                seq, t0, period, values, self.time_sync.quality, block.status
            )
            for d in self.spool.append(seq, t0, payload):
                self.events.emit(
                    logging.ERROR,
                    self.name,
                    "spool_full",
                    f"{d.reason}: dropped {d.batches} unacked batch(es), sequences "
                    f"{d.first_seq}..{d.last_seq}; the hub had not acked them (those it never "
                    "received are lost)",
                    first=d.first_seq,
                    last=d.last_seq,
                    batches=d.batches,
                    reason=d.reason,
                )
            pub = self._pub
            if pub is not None:
                pub.put(payload, attachment=encode_mark(self.spool.floor, self.spool.epoch))
            index += scans
            c.next_sequence = seq + 1
            c.batches += 1
            c.scans += scans

    def _time_restarted(self, restart: Restart, seq: int) -> None:
        """The device-time fit started over: say so, with how far sample times jumped."""
        self.events.emit(
            logging.WARNING if restart.jump_ns < 0 else logging.INFO,
            self.name,
            "time_restart",
            f"sample times from a new fit from sequence {seq}: {restart.why}; they "
            f"{'go back' if restart.jump_ns < 0 else 'jump ahead'} "
            f"{abs(restart.jump_ns) / 1e6:.3f} ms from where the batch before ended",
            sequence=seq,
            jump_ns=restart.jump_ns,
        )

    def _run_hook(
        self, hook: Callable[[npt.NDArray[np.float64]], None], values: npt.NDArray[np.float64]
    ) -> None:
        try:
            hook(values)
        except Exception as err:  # acquisition goes on; the failure is said loudly, once
            log.exception("%s: batch hook", self.name)
            if not self._hook_failed:
                self._hook_failed = True
                self.events.emit(
                    logging.CRITICAL,
                    self.name,
                    "interlock_error",
                    f"evaluating this stream's interlocks failed: {err!r}",
                )

    def _engineering(self, raw: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """raw * scale + offset per channel, as two flat passes: numpy broadcasts a short
        last axis row by row, three times slower than multiplying by a pre-tiled vector."""
        if self._tiled_scale.size != raw.size:
            scans = raw.shape[0]
            self._tiled_scale = np.tile(self.scale, scans)
            self._tiled_offset = np.tile(self.offset, scans)
            self._scratch = np.empty(raw.size)
        # Into one buffer kept across batches: a fresh 256 KB array per T8 batch costs page
        # faults. Its users (hooks, the encoder) are done with it before the next read.
        flat = np.multiply(raw.reshape(-1), self._tiled_scale, out=self._scratch)
        flat += self._tiled_offset
        return flat.reshape(raw.shape)

    def sync_spool(self) -> None:
        """fsync the spool; the agent calls this from its own thread, never the acquisition's."""
        try:
            self.spool.sync()
        except OSError as err:
            self.events.emit(logging.ERROR, self.name, "spool_error", f"spool fsync failed: {err}")

    def _replay(self) -> None:
        """Resend unacked batches from the spool, oldest first, rate-limited. A pass that
        fails (a spool read, a put) is reported and tried again: the thread never ends before
        the stream stops."""
        while not self._stop.wait(0.25):
            try:
                self._replay_pass()
            except Exception as err:
                if self._stop.is_set():
                    return  # the session closed under a put at shutdown: the spool keeps it
                log.exception("%s: replay", self.name)
                self.events.emit(
                    logging.ERROR,
                    self.name,
                    "replay_error",
                    f"replaying from the spool failed, trying again in 5 s: {err!r}",
                )
                self._stop.wait(5.0)

    def _replay_pass(self) -> None:
        after_ns = int(self.spool_cfg.replay_after_s * 1e9)
        rate = self.spool_cfg.replay_mb_per_s * 1e6
        window_s = 2.0  # > the hub's flush (ack) interval, or replay would stall on acks
        oldest = self.spool.oldest_unacked_time_ns()
        if oldest is None or time.time_ns() - oldest < after_ns:
            return
        if not self._hub_listens():
            return  # the hub is away: nothing to send to
        first, until = self.spool.acked + 1, self.counters.next_sequence - 1
        sent, batches, t_start = 0, 0, time.monotonic()
        window = window_s * rate  # bytes in flight beyond the last ack
        for seq, t_ns, payload in self.spool.read_from(first, until):
            if time.time_ns() - t_ns < after_ns:
                break  # recent batches went out live and their ack is still due
            # Keep the network queue short: wait for acks rather than piling up data ahead of
            # the live batches.
            while (seq - self.spool.acked) * len(payload) > window:
                if self._stop.wait(0.05) or not self._hub_listens():
                    break
            replay_pub = self._replay_pub  # set and cleared with `_pub` (`attach`)
            if self._stop.is_set() or not self._hub_listens() or replay_pub is None:
                break
            replay_pub.put(payload, attachment=encode_mark(self.spool.floor, self.spool.epoch))
            sent += len(payload)
            batches += 1
            self.counters.replayed += 1
            ahead = sent / rate - (time.monotonic() - t_start)
            if ahead > 0 and self._stop.wait(ahead):
                break
        if batches:
            log.info("%s: replayed %d batch(es) from sequence %d", self.name, batches, first)
        # Give the hub time to flush and ack before looking again.
        self._stop.wait(self.spool_cfg.replay_after_s)

    def stop(self) -> None:
        self._stop.set()
        self.driver.close()

    def join(self, timeout: float) -> None:
        for thread in (self._thread, self._replayer):
            if thread.is_alive():
                thread.join(timeout)
        if self._replayer.is_alive():
            # A replay put blocked on a congested link: the agent joins it again once its
            # session is closed (`join_replayer`), so no thread is inside Zenoh at exit.
            log.warning(
                "%s: replay still sending after %g s; waiting for the session", self.name, timeout
            )
        for pub in (self._pub, self._replay_pub):
            if pub is not None:
                pub.undeclare()
        self._pub = self._replay_pub = None
        self.spool.close()

    def join_replayer(self, timeout: float) -> None:
        """After the session is closed: the replay thread's blocked put has returned."""
        if self._replayer.is_alive():
            self._replayer.join(timeout)
            if self._replayer.is_alive():
                log.error("%s: the replay thread did not end", self.name)


def with_close(driver: Driver) -> None:
    try:
        driver.close()
    except (DriverError, OSError) as err:
        log.warning("closing driver: %s", err)

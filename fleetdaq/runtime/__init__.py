"""What the edge and the hub both run: worker threads that report their death (`threads`),
systemd notify and watchdog (`systemd`), per-system folders (`paths`, `writable`), TLS files
and certificate dates (`security`, `certificate_dates`), the Zenoh session (`zenoh_session`)
and host metrics (`host_metrics`). Above the contract, below the agent and the hub."""

from __future__ import annotations

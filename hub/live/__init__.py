"""The live-view wing: the dashboard and its API (`web`), the Foxglove WebSocket server
(`foxglove`), `/metrics` (`metrics`), decimated live plots (`plots`, `plot_kernels`), the
hub's status queryable (`status`) and the TLS of its web servers (`server_tls`). `wiring`
builds them."""

from __future__ import annotations

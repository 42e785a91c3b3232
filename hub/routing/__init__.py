"""The hub's embedded Zenoh router (`router`), its access control list generated from the site
file (`acl`), and what the router refuses, read from its log (`router_log`,
`refused_traffic`)."""

from __future__ import annotations

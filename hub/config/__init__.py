"""The hub-only parts of the site file: the hub section (`hub`), its recorder, snapshots and
partitions, alarms (`alarms`), rules and hub interlocks (`control`), notifications
(`notify`) and the dashboard (`dashboard`). Change a mail setting in `notify`."""

from __future__ import annotations

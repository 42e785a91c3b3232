"""The partitions wing: a partition hub records a slice of the nodes with its own router and
reports to the main hub (`runtime`); the main hub passes recorder requests and snapshot
triggers on (`recorders`, `snapshots`), watches the partitions (`watch`) and follows the
partition streams that its alarms and rules need (`live`). `wiring` builds them."""

from __future__ import annotations

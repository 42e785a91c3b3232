"""The partitions wing: a partition hub (`runtime`) records a slice of the nodes with its own
router, recorders (`recorders`) and snapshots (`snapshots`); the main hub watches the
partitions (`watch`) and follows the partition streams that its alarms and rules need
(`live`)."""

from __future__ import annotations

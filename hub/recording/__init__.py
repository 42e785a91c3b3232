"""The recording wing: the recorder thread and its MCAP files (`recorder`, `session`), the
batch feed from Zenoh (`batch_feed`), per-stream statistics and reports (`stream_stats`,
`stream_reports`), write-error recovery (`write_recovery`), start/stop/split requests
(`requests`), snapshots around alarms (`snapshots`), crash recovery and checks of files on
disk (`verify`) and the lock that gives a data folder to one hub (`data_lock`). `wiring` builds
them; what the wing needs of the others is typed in `seams`."""

from __future__ import annotations

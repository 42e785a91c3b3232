"""What the edge and the hub both speak: key expressions (`keys`), the messages and their
ROS 2 definitions (`messages`, `fleetdaq_msgs/`), the batch wire format (`wire`) and CDR
(`cdr`), the shared error tree (`errors`), the text rule for requesters (`requester_text`), the
site schema's shared parts (`schema`, `config`) and the driver registry (`drivers`).

It imports `fleetdaq.ptp` (a node's health carries its time status) and nothing else of
fleetdaq's: no agent, no hub, no runtime."""

from __future__ import annotations

"""``python -m fleetdaq``: the same as the `fleetdaq` command."""

from fleetdaq.cli import main

main()

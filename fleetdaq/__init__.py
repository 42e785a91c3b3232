"""The `fleetdaq` command (`fleetdaq.cli`): one module per sub-command group, each imported only
when its command runs, so `fleetdaq edge` on a Pi loads no hub code."""

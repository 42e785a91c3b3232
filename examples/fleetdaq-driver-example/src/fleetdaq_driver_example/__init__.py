"""An example fleetdaq driver package: a serial barometer (`serial_barometer`), its simulated
port with injectable faults, and the plugin object its `fleetdaq.drivers` entry point names."""

"""Alarms: definitions from the site file, the ISA-18.2 state machine, conditions over batches
(numpy) and over health (delays), the journal, and the supervisor service that runs them."""

"""The user's commands, one module each (demo, teach and run, calibrate, offline localize and
register, the bag view): they compose harness, missions and backends; ``mmpa.cli`` parses
the command line and calls one of them."""

"""Reading a circuit: its survey, the feeder zone, the device map's scaffold and its check."""

"""The embedded synthetic rural feeder, generated from a seed."""

"""Everything of the bridge that knows Zenoh: the loop, its runtime, the publishers, the oracle's serving, the command
line.
"""

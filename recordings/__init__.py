"""Recorder (Zenoh -> MCAP), info, recover, replay, and the offline re-run of the agent with a decision diff."""

"""Offline training: scenario selection (eq. 1-2), Algorithm 1 power flows, critical nodes, fits (eq. 3-5)."""

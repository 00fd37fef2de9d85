"""Simulators of both ends of the EG-Link on an abstract clock and transport (TS-0006 section 5)."""

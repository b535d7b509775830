"""Replay publishers for the bundled real recordings (BROAD, the car circles, the indoor walks)."""

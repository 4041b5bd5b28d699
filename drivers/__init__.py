"""Drivers: move bytes to and from hardware and enforce hardware safety. Never decide control."""

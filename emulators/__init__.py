"""Emulators: numpy plants behind the same wire protocols as the real hardware."""

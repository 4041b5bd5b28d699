"""Foxglove layouts of the live view and of recorded sessions (``hil layout``)."""

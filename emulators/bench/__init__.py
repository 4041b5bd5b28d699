"""The relay bench emulated: plant and Modbus server."""

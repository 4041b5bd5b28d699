"""The relay bench's driver: Modbus I/O and the safety layer that is its Device."""

"""EtherCAT: hil's software slave (an ESC skin over the emulated drive) on a raw socket."""

"""The links a line talks through: serial ports (with their UART counters) and TCP."""

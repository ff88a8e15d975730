"""The I/O shell: sockets, serial ports, the event loop, deadlines and queues."""

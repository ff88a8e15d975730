"""Where masters come in: the Modbus TCP, TLS, RTU-over-TCP and serial-slave listeners,
the source screen, and the spine that carries out admission's decision for all of them."""

"""modbus-gateway: a Modbus TCP to Modbus RTU gateway."""

__version__ = "0.1.0"

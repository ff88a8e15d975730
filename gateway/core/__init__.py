"""The protocol core: bytes in, frames and decisions out; no I/O, no clock, no logging."""

"""The line driver: the bus that runs a line's core, its port, its notes and tallies."""

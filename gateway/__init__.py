"""modbus-gateway: a Modbus TCP to Modbus RTU gateway."""

__version__ = "0.1.0"


def build() -> str:
    """``"compiled"`` when the hot path runs as mypyc extensions (see setup.py), else
    ``"interpreted"``: operators and benchmarks need to know which one they measure."""
    from importlib.machinery import EXTENSION_SUFFIXES

    from .core import line

    return "compiled" if line.__file__.endswith(tuple(EXTENSION_SUFFIXES)) else "interpreted"

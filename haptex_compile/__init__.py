"""haptex compiler: texture sources -> tactile assets (HAPTEX method)."""

__version__ = "0.1.0"

"""haptex compiler: texture sources -> tactile assets (HAPTEX method)."""

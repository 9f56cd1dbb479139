"""Benchmark scripts: speed and accuracy figures, printed (not asserted)."""

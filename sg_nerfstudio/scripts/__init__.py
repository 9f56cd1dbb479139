"""Console scripts (thin tyro wrappers around the library)."""

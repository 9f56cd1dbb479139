"""Real photographs: a folder of photos -> working images -> pycolmap SfM -> meta-images, and the real-photo
benchmark scene builder (see ARCHITECTURE.md)."""

"""Geometry shared by every stage: `sim3` (the Sim3 value type, moving cameras), `frames` (OpenCV / OpenGL
camera conventions), `meta_image` (reading a meta-image: photos + COLMAP model, undistortion)."""

"""Registration of meta-images to a frozen sg-feature-splat reference model (paper section 3).

One module per stage: `meta_image` (read + validate + undistort), `reference` (load the frozen model and
render it), `sim3` (transforms and the 7-parameter update), `robust` (per-image losses, LTS and
ablations), `optimize` (the loop), `metrics` (ΔR, ΔT, MTA, O%), `outputs` (files and report).
"""

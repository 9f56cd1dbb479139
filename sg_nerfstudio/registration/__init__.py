"""Registration of meta-images to a frozen sg-feature-splat reference model (paper section 3).

One module per role: `settings` (RegistrationSettings and the shipped presets), `reference` (load the
frozen model and render it), `objectives` (features / teacher-on-render / photometric: targets, renders,
per-photo losses), `robust` (LTS and its ablations), `optimize` (`register()`: the anchored start, the
stages, the verdict's evidence), `stages` (one stage's Adam loop), `schedules` (the photos of each step,
the history), `hypotheses` (several starts), `scale_search` (the scale the anchors leave free), `session`
(several meta-images as ns-register-meta runs them), `outputs` (files and report), `metrics` (ΔR, ΔT,
MTA, O%), `merge` (every aligned meta-image in one COLMAP model); ARCHITECTURE.md lists the rest.
"""

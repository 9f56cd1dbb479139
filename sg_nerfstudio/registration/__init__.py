"""Registration of meta-images to a frozen sg-feature-splat reference model (paper section 3).

One module per role: `settings` (RegistrationSettings in groups, the shipped presets), `reference` (load the frozen
model and render it), `objectives` (features / teacher-on-render / photometric: targets, renders, per-photo losses),
`robust` (LTS and its ablations), `optimize` (`register()`: the anchored start, the stages, the verdict's evidence),
`anchored_start/` (keypoint anchors, pre-alignment, camera fit, scale search: one entry, `start_from_anchors`),
`stages` (one stage's Adam loop), `schedules` (the photos of each step, the history), `hypotheses` (several starts),
`verdict` (registered / uncertain / failed), `session` (several meta-images as ns-register-meta runs them), `outputs`
(files and report), `metrics` (ΔR, ΔT, MTA, O%), `merge` (every aligned meta-image in one COLMAP model).
"""

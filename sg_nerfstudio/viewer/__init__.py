"""Registrations inside nerfstudio's viewer: `inputs` (result directories -> registrations), `scene`
(frustums, toggles, photo | render panel), `session` (start nerfstudio's Viewer with them, stop it cleanly)."""

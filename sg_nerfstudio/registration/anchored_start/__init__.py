"""The anchored start: where keypoint anchors exist, the render-free steps that put a meta-image where its anchors say
before anything is rendered. One entry, `start_from_anchors` (start.py), in this order:

1. `anchors`: the SIFT initialisers' verified 2D-3D matches as a robust reprojection term (`Anchoring`, `KeypointTerm`),
   minimised alone from the given start (the pre-alignment: Adam, a few milliseconds a step);
2. `camera_fit`: the meta-image's own cameras (focal lengths, poses, k1) fitted with the Sim(3): under the SfM's own
   priors by Levenberg-Marquardt (`least_squares`), or, where it applies, as one pycolmap bundle adjustment of the
   meta-image's tracks with the anchors (`bundle_adjustment`); a fit beyond what an SfM of a few photos errs by is refused;
3. `scale_search`: where the anchors leave the scale free (one photo's, or photos from one spot), the scale the other
   photos' dense objective prefers.

The rendered stages then use the same anchors as a term of their objective (registration/stages.py).
"""

from sg_nerfstudio.registration.anchored_start.anchors import Anchoring, KeypointTerm, anchors_fix_scale
from sg_nerfstudio.registration.anchored_start.start import AnchoredStart, prealigns, start_from_anchors

__all__ = ["AnchoredStart", "Anchoring", "KeypointTerm", "anchors_fix_scale", "prealigns", "start_from_anchors"]

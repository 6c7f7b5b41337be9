"""Visual front-end: point observations from RGB-D frames.

Corners are detected and tracked from frame to frame in the colour image (:mod:`.tracking`), then
lifted into the camera frame with the depth at their pixel (:mod:`.backprojection`). The result is one
:class:`~relpoint.types.PointObservation` per frame whose ``ids`` are persistent track ids, so that every
point estimator can run on real camera data. No file I/O happens here.
"""

from relpoint.frontend.backprojection import back_project, depth_at_pixels
from relpoint.frontend.keypoints import KeypointFrontEnd
from relpoint.frontend.tracking import KeypointSettings, KeypointTracker

__all__ = ["KeypointFrontEnd", "KeypointSettings", "KeypointTracker", "back_project", "depth_at_pixels"]

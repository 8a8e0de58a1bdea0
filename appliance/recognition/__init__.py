"""Posture recognition: from a biplane pair of X-ray frames to the robot's 3D position and axis.

The pipeline, one module per stage (each stage is a plain function, so it can be timed alone):

* :mod:`.background` - the open-field background ``log B``, kept coarse (:func:`log_background`);
* :mod:`.segmentation` - attenuation image, robot candidates in a region of interest (:func:`segment`);
* :mod:`.detection` - robot candidates anywhere in the frame, coarse to fine (:func:`detect`);
* :mod:`.features` - PCA features per view (:func:`weighted_features`, the paper's :func:`paper_features`);
* :mod:`.correspondence` - tip pairing cases A/B by geometric epipolar distance (:func:`choose_pairing`);
* :mod:`.reconstruction` - centroid, axis, tips, head, length (:func:`reconstruct`);
* :mod:`.body_prior` - the robot's known body placed on the axis: centroid and tips (:func:`place_body`);
* :mod:`.head_by_body` - the head told by the known body's shape where the ramps do not tell it (:func:`chi2_of`
  the body's fit with its apex at either end; compiled in :mod:`.head_kernels`);
* :mod:`.body_corrections` - a reconstruction corrected by the known body: the head, an unresolved mirror
  ambiguity, an axis in an epipolar plane (:func:`.body_corrections.head_by_body` and the others; the plane
  scan's fits compiled in :mod:`.axis_kernels`);
* :mod:`.roi_search` - the tracked robot's blob and features in one view's ROI, one compiled call
  (:mod:`.roi_kernels`) giving what segment + gate + features give;
* :mod:`.tracker` - ROI tracking over frames (:class:`PostureTracker`), producing :class:`Posture` records.
"""
from __future__ import annotations

from appliance.recognition.correspondence import Pairing, choose_pairing, pair_candidates, pairing_rms
from appliance.recognition.features import (
    Features2D,
    axial_profile,
    features,
    paper_features,
    paper_features_from_points,
    weighted_features,
    weighted_moments,
)
from appliance.recognition.posture import Posture, ViewObservation
from appliance.recognition.reconstruction import Reconstruction, reconstruct
from appliance.recognition.segmentation import (
    Blob,
    LogBackground,
    Roi,
    attenuation,
    log_background,
    noise_sigma,
    segment,
)
from appliance.recognition.detection import detect
from appliance.recognition.settings import RecognitionSettings
from appliance.recognition.tracker import PostureTracker

__all__ = [
    "Blob", "Features2D", "LogBackground", "Pairing", "Posture", "PostureTracker", "RecognitionSettings",
    "Reconstruction", "Roi", "ViewObservation", "attenuation", "axial_profile", "choose_pairing", "detect",
    "features", "log_background", "noise_sigma", "pair_candidates", "pairing_rms", "paper_features",
    "paper_features_from_points", "reconstruct", "segment", "weighted_features", "weighted_moments",
]

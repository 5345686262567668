"""The paper's recipe: landmark pre-alignment and the normals + landmarks fit, single- and multi-view."""

from facenormals.fitting.fit import FacingAwayWarning, FitResult, NormalAxisError, fit_head
from facenormals.fitting.landmark_visibility import drop_hidden_landmarks, hidden_landmarks
from facenormals.fitting.pose import FACING_AWAY_COSINE, PoseEstimate, facing_cosine, landmark_pose_jacobian, prealign_pose
from facenormals.fitting.problem import FitWeights, HeadFitProblem
from facenormals.fitting.subsample import grid_subset

__all__ = [
    "FACING_AWAY_COSINE",
    "FacingAwayWarning",
    "FitResult",
    "FitWeights",
    "HeadFitProblem",
    "NormalAxisError",
    "PoseEstimate",
    "drop_hidden_landmarks",
    "facing_cosine",
    "fit_head",
    "grid_subset",
    "hidden_landmarks",
    "landmark_pose_jacobian",
    "prealign_pose",
]

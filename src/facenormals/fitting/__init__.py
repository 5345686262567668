"""The paper's recipe: landmark pre-alignment and the normals + landmarks fit, single- and multi-view."""

from facenormals.fitting.fit import FitResult, fit_head
from facenormals.fitting.pose import PoseEstimate, landmark_pose_jacobian, prealign_pose
from facenormals.fitting.problem import FitWeights, HeadFitProblem

__all__ = ["FitResult", "FitWeights", "HeadFitProblem", "PoseEstimate", "fit_head", "landmark_pose_jacobian", "prealign_pose"]

"""Network: a U-Net from a photo to a normal map, landmark maps and a foreground mask, and its loss."""

from facenormals.nn.loss import normal_landmark_loss
from facenormals.nn.unet import NormalLandmarkUNet, UNetOutput

__all__ = ["NormalLandmarkUNet", "UNetOutput", "normal_landmark_loss"]

"""Network: a U-Net from a photo to a normal map, landmark maps and a foreground mask, its loss and weights."""

from facenormals.nn.loss import normal_landmark_loss
from facenormals.nn.mirror import mirror_averaged, mirror_output, mirror_permutation
from facenormals.nn.pretrained import load_weights, pretrained_weights_path, update_weight_metadata
from facenormals.nn.unet import NormalLandmarkUNet, UNetOutput

__all__ = ["NormalLandmarkUNet", "UNetOutput", "load_weights", "mirror_averaged", "mirror_output", "mirror_permutation",
           "normal_landmark_loss", "pretrained_weights_path", "update_weight_metadata"]

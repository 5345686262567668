"""From photos to a head: reading, face detection and cropping, the network, the fit and the output files.

``facenormals reconstruct photo.jpg -o out`` runs :func:`reconstruct_photos`; see
``docs/tutorials/reconstruct.md``.
"""

from facenormals.reconstruct.detect import FaceBox, NoFaceError, crop_square, detect_faces, head_crop_box
from facenormals.reconstruct.images import ImageReadError, read_image
from facenormals.reconstruct.photos import prepare_view, reconstruct_photos
from facenormals.reconstruct.pipeline import (
    NETWORK_FIT_WEIGHTS,
    FitInputs,
    NetworkMaps,
    PhotoView,
    Reconstruction,
    fit_inputs,
    landmark_channels,
    network_fit_weights,
    predict_maps,
    reconstruct_views,
    write_reconstruction,
)

__all__ = [
    "FaceBox",
    "FitInputs",
    "ImageReadError",
    "NETWORK_FIT_WEIGHTS",
    "NetworkMaps",
    "NoFaceError",
    "PhotoView",
    "Reconstruction",
    "crop_square",
    "detect_faces",
    "fit_inputs",
    "head_crop_box",
    "landmark_channels",
    "network_fit_weights",
    "predict_maps",
    "prepare_view",
    "read_image",
    "reconstruct_photos",
    "reconstruct_views",
    "write_reconstruction",
]

"""The public names are recorded here, so removing or renaming one is a conscious act."""

import importlib

import pytest

import facenormals

PUBLIC = {
    "facenormals.core": ["atomic_write", "check_finite", "check_floating", "check_nonnegative", "check_same_dims", "check_shape", "check_tensor"],
    "facenormals.geometry": ["euler_rotation_derivatives", "euler_to_rotation_matrix", "project_points",
                             "projection_jacobian", "rotation_matrix_to_euler", "transform_points"],
    "facenormals.mesh": ["VertexNormals", "VertexNormalsJacobian", "load_mesh", "save_mesh", "vertex_normals",
                         "vertex_normals_jvp"],
    "facenormals.models": ["BUILTIN_PARAMETERS", "LANDMARK_NAMES", "LANDMARK_PAIRS", "ModelFileError",
                           "MorphableModel", "builtin_head_model", "fetch_ict", "find_ict_archive", "ict_release_differences", "load_bfm2009",
                           "load_bfm2017", "load_flame", "load_ict_npz", "load_ict_raw", "load_lyhm", "load_model"],
    "facenormals.sampling": ["BicubicSampler", "sample_bicubic", "sample_bicubic_with_gradient"],
    "facenormals.render": ["Fragments", "draw_alignment", "interpolate_vertex_attributes", "normal_map_to_image", "rasterize_depth", "rasterize_triangles",
                           "render_normal_map", "render_shaded", "shade_normal_map", "splat_zbuffer", "unoccluded_points",
                           "visible_vertices"],
    "facenormals.energy": ["landmark_residuals", "normal_residuals", "prior_residuals"],
    "facenormals.optim": ["LMResult", "LMStatus", "levenberg_marquardt", "normal_equations"],
    "facenormals.nn": ["NormalLandmarkUNet", "UNetOutput", "load_weights", "mirror_averaged", "mirror_output",
                       "mirror_permutation", "normal_landmark_loss", "pretrained_weights_path",
                       "update_weight_metadata"],
    "facenormals.training": ["NetworkMetrics", "TrainConfig", "TrainSummary", "calibrate_landmark_threshold",
                             "evaluate_network", "export_weights", "landmark_threshold", "load_checkpoint",
                             "normal_angles", "save_checkpoint", "train"],
    "facenormals.reconstruct": ["FaceBox", "FitInputs", "ImageReadError", "NETWORK_FIT_WEIGHTS", "NetworkMaps", "NoFaceError",
                                "PhotoView", "Reconstruction", "crop_square", "detect_faces", "fit_inputs", "head_crop_box",
                                "landmark_channels", "network_fit_weights", "predict_maps",
                                "prepare_view", "read_image", "reconstruct_photos", "reconstruct_views",
                                "write_reconstruction"],
    "facenormals.data": ["HEAD_LABELS", "HeadlessGLError", "LABELS", "PhotoAugmentation", "SynthBatch", "SynthConfig",
                         "SynthSummary", "SyntheticHeadDataset", "SyntheticHeadGenerator", "blocked_rays", "landmark_maps",
                         "landmarks_from_maps", "random_background", "read_manifest", "select_gl_platform",
                         "write_dataset"],
    "facenormals.eval": ["AlignmentResult", "DEFAULT_ALIGNMENT_LANDMARKS", "DepthStatistics", "EvaluationReport",
                         "ICPResult", "apply_similarity", "closest_points_on_mesh", "correspondence_errors",
                         "depth_errors", "depth_statistics", "evaluate_reconstruction", "fit_similarity",
                         "icp_point_to_plane", "landmark_correspondences", "point_to_plane_errors", "shares_vertex_order",
                         "summarise"],
    "facenormals.fitting": ["FACING_AWAY_COSINE", "FacingAwayWarning", "FitResult", "FitWeights", "HeadFitProblem", "NormalAxisError", "PoseEstimate",
                            "drop_hidden_landmarks", "facing_cosine", "fit_head", "grid_subset", "hidden_landmarks",
                            "landmark_pose_jacobian", "prealign_pose"],
    # used by examples/ (paper_pipeline.py, demo_synthetic_fit.py) and the `demo` command
    "facenormals.fitting.oracle": ["OracleViews", "render_oracle_views"],
    "facenormals.demo": ["DemoReport", "run_demo"],
}

# The names the foundation issue makes binding: importable from the top level and their subpackage.
BINDING = {
    "MorphableModel": "facenormals.models",
    "vertex_normals": "facenormals.mesh",
    "VertexNormals": "facenormals.mesh",
    "euler_to_rotation_matrix": "facenormals.geometry",
    "rotation_matrix_to_euler": "facenormals.geometry",
    "project_points": "facenormals.geometry",
    "sample_bicubic": "facenormals.sampling",
    "normal_residuals": "facenormals.energy",
    "landmark_residuals": "facenormals.energy",
    "prior_residuals": "facenormals.energy",
    "levenberg_marquardt": "facenormals.optim",
    "LMResult": "facenormals.optim",
    "NormalLandmarkUNet": "facenormals.nn",
}


@pytest.mark.parametrize("module", sorted(PUBLIC))
def test_subpackage_all(module):
    mod = importlib.import_module(module)
    assert sorted(mod.__all__) == sorted(PUBLIC[module])
    assert list(mod.__all__) == sorted(mod.__all__), "__all__ is kept sorted"
    for name in mod.__all__:
        assert hasattr(mod, name)


@pytest.mark.parametrize("name,module", sorted(BINDING.items()))
def test_binding_names(name, module):
    assert getattr(facenormals, name) is getattr(importlib.import_module(module), name)


def test_top_level_all_is_sorted_and_importable():
    assert list(facenormals.__all__) == sorted(facenormals.__all__)
    assert len(set(facenormals.__all__)) == len(facenormals.__all__)
    for name in facenormals.__all__:
        assert hasattr(facenormals, name), name

import pytest
import torch

from facenormals.mesh import load_mesh, save_mesh
from facenormals.models import builtin_head_model


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_round_trip_keeps_vertex_order(tmp_path, suffix):
    model = builtin_head_model()
    path = save_mesh(tmp_path / f"head{suffix}", model.mean[None], model.faces)
    vertices, faces = load_mesh(path)
    assert torch.allclose(vertices, model.mean, atol=1e-4)
    assert torch.equal(faces, model.faces)


def test_model_export(tmp_path):
    model = builtin_head_model()
    model.export_mesh(tmp_path / "mean.obj")
    model.export_mesh(tmp_path / "sample.ply", model.shape_std)
    v, _ = load_mesh(tmp_path / "sample.ply")
    assert torch.allclose(v, model(model.shape_std[None])[0], atol=1e-4)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(ValueError, match="missing.ply: mesh file not found"):
        load_mesh(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\x00\x01")
    with pytest.raises(ValueError, match="bad.ply"):
        load_mesh(bad)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(N, 3\)"):
        save_mesh(tmp_path / "x.ply", torch.zeros(4, 2), torch.tensor([[0, 1, 2]]))

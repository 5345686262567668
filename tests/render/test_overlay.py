import numpy as np
import pytest
import torch

from facenormals.render import draw_alignment, normal_map_to_image


def test_overlay_draws_points_and_writes_png(tmp_path):
    image = np.zeros((16, 16, 3), np.uint8)
    out = draw_alignment(image, torch.tensor([[3.0, 4.0], [10.0, 12.0]]), torch.tensor([[8.0, 8.0], [float("nan"), 1.0]]),
                         path=tmp_path / "o.png", scale=4)
    assert out.shape == (64, 64, 3) and (tmp_path / "o.png").exists()
    assert out[4 * 4 + 1, 3 * 4 + 1].sum() > 0  # the vertex dot at pixel (3, 4)
    assert out[0, 0].sum() == 0


def test_overlay_bad_image():
    with pytest.raises(ValueError, match="image"):
        draw_alignment(np.zeros((4, 4, 3), np.float32), torch.zeros(1, 2))


def test_normal_map_colours():
    nmap = torch.zeros(3, 1, 2)
    nmap[:, 0, 0] = torch.tensor([0.0, -1.0, 0.0])  # up (y is down)
    img = normal_map_to_image(nmap)
    assert img[0, 0].tolist() == [128, 255, 128] and img[0, 1].tolist() == [0, 0, 0]

"""A small in-memory dataset with the items of SyntheticHeadDataset, for fast training tests."""

from __future__ import annotations

import torch
from torch.utils.data import Dataset


class TinyHeads(Dataset):
    """Discs on noise: the disc is the foreground with a sphere-like normal field, 24 landmarks on it."""

    def __init__(self, count: int = 24, size: int = 32, seed: int = 0) -> None:
        g = torch.Generator().manual_seed(seed)
        self.items = []
        v, u = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32),
                              indexing="ij")
        for i in range(count):
            cx, cy = (torch.rand(2, generator=g) * size * 0.3 + size * 0.35).tolist()
            r = size * 0.3
            dx, dy = (u - cx) / r, (v - cy) / r
            inside = dx**2 + dy**2 < 1
            nz = -torch.sqrt((1 - dx**2 - dy**2).clamp(min=0))
            normals = torch.stack([dx, dy, nz]) * inside
            image = torch.rand(3, size, size, generator=g) * 0.2 + 0.6 * inside
            angle = torch.rand(24, generator=g) * 6.283
            points = torch.stack([cx + 0.6 * r * torch.cos(angle), cy + 0.6 * r * torch.sin(angle)], -1)
            visible = torch.rand(24, generator=g) > 0.2
            self.items.append({"image": image.clamp(0, 1), "normals": normals, "foreground": inside[None],
                               "landmarks": points, "landmark_visible": visible, "index": torch.tensor(i)})

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        return self.items[i]


class BrokenHeads(TinyHeads):
    """Every item fails to load, as a corrupt shard does (picklable for DataLoader workers)."""

    def __getitem__(self, i: int) -> dict:
        raise ValueError(f"shard_00000.npz: sample {i} is damaged")

"""Draw docs/img/synth_grid.png: synthetic training samples, one per column: image, normal map N, landmark maps Z.

    python docs/scripts/make_synth_figure.py [--model auto] [--seed 0] [--columns 8] [--rows 2]
"""

from __future__ import annotations

import argparse
import colorsys
from pathlib import Path

import numpy as np
import torch

from facenormals.data import SyntheticHeadGenerator, landmark_maps
from facenormals.render import normal_map_to_image


def landmark_image(points: np.ndarray, visible: np.ndarray, size: int) -> np.ndarray:
    """The 24 landmark maps as one RGB image: each channel in its own hue, brightest channel wins."""
    maps = landmark_maps(torch.from_numpy(points)[None], torch.from_numpy(visible)[None], (size, size))[0].numpy()
    hues = np.array([colorsys.hsv_to_rgb(k / len(maps), 0.85, 1.0) for k in range(len(maps))])
    strongest = maps.argmax(0)
    value = maps.max(0)
    return (hues[strongest] * value[..., None] * 255).astype(np.uint8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="auto")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--columns", type=int, default=8)
    parser.add_argument("--rows", type=int, default=2, help="groups of (image, N, Z) rows")
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "img" / "synth_grid.png"))
    args = parser.parse_args()
    import cv2

    count = args.columns * args.rows
    with SyntheticHeadGenerator(args.model) as generator:
        batch = generator.generate(args.seed, range(count))
    size = batch.image.shape[1]
    gap = 4
    blocks = []
    for r in range(args.rows):
        lines = [[], [], []]
        for c in range(args.columns):
            i = r * args.columns + c
            lines[0].append(batch.image[i])
            lines[1].append(normal_map_to_image(torch.from_numpy(batch.normals[i])))
            lines[2].append(landmark_image(batch.landmarks[i], batch.landmark_visible[i], size))
        spacer = np.full((size, gap, 3), 255, np.uint8)
        rows = []
        for line in lines:
            row = [line[0]]
            for image in line[1:]:
                row += [spacer, image]
            rows.append(np.concatenate(row, axis=1))
        block = np.concatenate([rows[0], np.full((gap, rows[0].shape[1], 3), 255, np.uint8), rows[1],
                                np.full((gap, rows[0].shape[1], 3), 255, np.uint8), rows[2]])
        blocks.append(block)
    figure = blocks[0]
    for block in blocks[1:]:
        figure = np.concatenate([figure, np.full((3 * gap, figure.shape[1], 3), 255, np.uint8), block])
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, cv2.cvtColor(figure, cv2.COLOR_RGB2BGR))
    print(f"wrote {args.out} ({generator.model.name}, seed {args.seed}, samples 0..{count - 1})")


if __name__ == "__main__":
    main()

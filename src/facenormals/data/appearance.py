"""Colours and lights: skin tones, hair and eye colours, colour temperature, procedural variation.

All colours handed to the renderer are **linear** RGB; palettes are written in sRGB and converted
with :func:`srgb_to_linear`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from facenormals.data.render import Lighting, MeshPart

__all__ = [
    "EXPOSURE_PERCENTILE",
    "HAIR_COLORS",
    "SKIN_TONES",
    "auto_exposure",
    "color_temperature",
    "fourier_noise",
    "sample_lighting",
    "skin_albedo",
    "srgb_to_linear",
]

#: The ten Monk Skin Tone scale swatches (sRGB 0..255), lightest to darkest.
SKIN_TONES = np.array([
    (246, 237, 228), (243, 231, 219), (247, 234, 208), (234, 218, 186), (215, 189, 150),
    (160, 126, 86), (130, 92, 67), (96, 65, 52), (58, 49, 42), (41, 36, 32),
], dtype=np.float64) / 255.0  # fmt: skip

#: Natural hair colours (sRGB), black to white, plus a few dyed ones at the end.
HAIR_COLORS = np.array([
    (20, 17, 15), (38, 28, 22), (59, 41, 30), (86, 60, 40), (120, 86, 55), (160, 120, 75),
    (200, 165, 110), (225, 200, 150), (140, 60, 30), (175, 90, 45), (150, 150, 150), (215, 215, 210),
    (120, 30, 60), (40, 60, 130), (180, 60, 120),
], dtype=np.float64) / 255.0  # fmt: skip
_HAIR_WEIGHTS = np.array([10, 10, 9, 8, 6, 4, 3, 2, 2, 2, 3, 2, 0.5, 0.5, 0.5], dtype=np.float64)

#: Iris colours (sRGB): browns, hazel, green, blue, grey.
IRIS_COLORS = np.array([
    (60, 35, 20), (90, 55, 30), (120, 80, 40), (110, 100, 50), (70, 110, 70), (70, 110, 160), (110, 140, 170),
    (100, 105, 110),
], dtype=np.float64) / 255.0  # fmt: skip
_IRIS_WEIGHTS = np.array([10, 8, 4, 3, 2, 3, 2, 1], dtype=np.float64)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB in ``[0, 1]`` to linear RGB (the standard piecewise curve)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def color_temperature(kelvin: float) -> np.ndarray:
    """Linear-RGB colour of a black body at ``kelvin`` (1000..40000 K), scaled to a maximum of 1.

    Uses Tanner Helland's fit of the CIE 1964 black-body colours (sRGB), linearised.

    Example:
        >>> np.round(color_temperature(6600), 1)  # about white
        array([1., 1., 1.])
        >>> bool(color_temperature(3000)[2] < 0.3)  # warm light has little blue
        True
    """
    t = float(np.clip(kelvin, 1000.0, 40000.0)) / 100.0
    if t <= 66:
        r = 255.0
        g = 99.4708025861 * np.log(t) - 161.1195681661
        b = 0.0 if t <= 19 else 138.5177312231 * np.log(t - 10) - 305.0447927307
    else:
        r = 329.698727446 * (t - 60) ** -0.1332047592
        g = 288.1221695283 * (t - 60) ** -0.0755148492
        b = 255.0
    rgb = srgb_to_linear(np.clip([r, g, b], 0.0, 255.0) / 255.0)
    return rgb / rgb.max()


def fourier_noise(points: np.ndarray, rng: np.random.Generator, wavelength: float, terms: int = 12) -> np.ndarray:
    """Smooth random field on ``points`` ``(N, 3)`` (mm): a sum of random plane waves, unit variance.

    The waves have random directions and wavelengths around ``wavelength`` mm.
    """
    directions = rng.normal(size=(terms, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    k = 2.0 * np.pi / (wavelength * rng.uniform(0.7, 1.4, size=(terms, 1)))
    phase = rng.uniform(0.0, 2.0 * np.pi, size=terms)
    return np.sin(points @ (directions * k).T + phase).sum(axis=1) * np.sqrt(2.0 / terms)


def sample_skin_tone(rng: np.random.Generator) -> np.ndarray:
    """A base skin colour (linear RGB) anywhere along the Monk scale, with a small hue jitter."""
    position = rng.uniform(0.0, len(SKIN_TONES) - 1.0)
    k = min(int(position), len(SKIN_TONES) - 2)
    srgb = SKIN_TONES[k] * (1 - (position - k)) + SKIN_TONES[k + 1] * (position - k)
    srgb = srgb * np.array([1.0 + rng.normal(0, 0.03), 1.0 + rng.normal(0, 0.025), 1.0 + rng.normal(0, 0.04)])
    return srgb_to_linear(np.clip(srgb, 0.0, 1.0))


_NATURAL_HAIR = 12  # HAIR_COLORS[:12] are natural, the rest dyed


def sample_hair_color(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A hair colour and a matching eyebrow/beard colour (linear RGB).

    Natural colours are far more likely than dyed ones; brows and beards take a darker natural
    colour (dyed hair gets brown brows, grey and blond hair a little darker brows).
    """
    k = rng.choice(len(HAIR_COLORS), p=_HAIR_WEIGHTS / _HAIR_WEIGHTS.sum())
    hair = srgb_to_linear(np.clip(HAIR_COLORS[k] * rng.uniform(0.85, 1.15, size=3), 0.0, 1.0))
    natural = k if k < _NATURAL_HAIR else int(rng.integers(0, 5))
    brows = srgb_to_linear(np.clip(HAIR_COLORS[natural] * rng.uniform(0.6, 0.9), 0.0, 1.0))
    return hair, brows


def sample_iris_color(rng: np.random.Generator) -> np.ndarray:
    k = rng.choice(len(IRIS_COLORS), p=_IRIS_WEIGHTS / _IRIS_WEIGHTS.sum())
    return srgb_to_linear(np.clip(IRIS_COLORS[k] * rng.uniform(0.8, 1.2, size=3), 0.0, 1.0))


def skin_albedo(
    noise: Callable[[np.random.Generator, str], np.ndarray], regions: dict[str, np.ndarray], rng: np.random.Generator,
    brow_color: np.ndarray,
) -> np.ndarray:
    """Per-vertex skin albedo ``(N, 3)`` (linear RGB) with procedural variation.

    A base tone from the Monk scale, modulated by smooth noise at three scales (blotches, mottling,
    grain), redder cheeks, nose and ears, lips (sometimes lipstick), darker under-eyes, eyebrows,
    and sometimes stubble/beard and freckles.

    Args:
        noise: ``noise(rng, name)`` gives a unit-variance per-vertex field at the scale ``name``
            (see :meth:`~facenormals.data.head.HeadAssets.noise`).
        regions: per-vertex region weights (:attr:`~facenormals.data.head.HeadAssets.regions`).
        rng: the random stream.
        brow_color: linear-RGB colour of eyebrows and beard.
    """
    tone = sample_skin_tone(rng)
    darkness = 1.0 - float(np.mean(tone) ** 0.5)
    variation = (0.06 * noise(rng, "blotches") + 0.04 * noise(rng, "mottle")
                 + 0.03 * rng.uniform(0.3, 1.0) * noise(rng, "grain"))
    albedo = tone[None, :] * (1.0 + variation[:, None])
    redness = np.array([0.0, 0.22, 0.22])
    flush = rng.uniform(0.0, 0.45) * regions["cheeks"] + rng.uniform(0.05, 0.35) * regions["nose"] + 0.3 * regions["ears"]
    albedo *= 1.0 - flush[:, None] * redness[None, :]
    albedo *= 1.0 - rng.uniform(0.0, 0.3) * regions["under_eyes"][:, None] * np.array([0.9, 1.0, 0.9])
    lip = tone * np.array([0.75, 0.42, 0.45]) * rng.uniform(0.7, 1.1)
    if rng.random() < 0.15:  # lipstick
        lip = srgb_to_linear(rng.uniform([0.4, 0.0, 0.05], [0.85, 0.2, 0.35]))
    w = np.clip(regions["lips"] * rng.uniform(0.6, 1.0), 0, 1)[:, None]
    albedo = albedo * (1 - w) + lip[None, :] * w
    brow_density = rng.uniform(0.3, 0.95) * (1.0 - 0.5 * darkness)
    w = np.clip(regions["brows"] * brow_density * (0.75 + 0.25 * noise(rng, "hairs")), 0, 1)[:, None]
    albedo = albedo * (1 - w) + brow_color[None, :] * w
    if rng.random() < 0.3:
        beard = rng.uniform(0.15, 0.9)
        w = np.clip(regions["beard"] * beard * (0.8 + 0.2 * noise(rng, "stubble")), 0, 1)[:, None]
        albedo = albedo * (1 - w) + brow_color[None, :] * w
    if rng.random() < 0.15:
        spots = np.clip(noise(rng, "freckles") - 1.2, 0, 1) * regions["face"]
        albedo *= 1.0 - rng.uniform(0.1, 0.3) * spots[:, None] * np.array([0.8, 1.0, 1.2])[None, :]
    return np.clip(albedo, 0.0, 1.0).astype(np.float32)


def sample_lighting(rng: np.random.Generator, num_lights: tuple[int, int] = (1, 3),
                    temperature: tuple[float, float] = (2500.0, 9000.0)) -> Lighting:
    """Ambient light plus 1–3 directional lights with random directions, intensities and colour temperatures.

    Directions are in the camera frame (x right, y down, z forward) and point from the subject to the
    light; the key light comes from the camera's side of the subject (97 % of draws; else a rim
    light from behind), each fill light from the camera's side in 80 % of draws and from behind
    otherwise, all slightly favouring above.
    """
    count = int(rng.integers(num_lights[0], num_lights[1] + 1))
    directions, colors = [], []
    for k in range(count):
        while True:
            d = rng.normal(size=3)
            d[1] -= 0.4  # from above more often
            d[2] = -abs(d[2]) * (1.5 if k == 0 else 1.0) if rng.random() < (0.97 if k == 0 else 0.8) else abs(d[2])
            norm = np.linalg.norm(d)
            if norm > 1e-3:
                break
        directions.append(d / norm)
        intensity = rng.uniform(0.6, 1.5) if k == 0 else rng.uniform(0.1, 0.8)
        colors.append(color_temperature(rng.uniform(*temperature)) * intensity)
    ambient = color_temperature(rng.uniform(*temperature)) * rng.uniform(0.12, 0.55)
    return Lighting(ambient=ambient, directions=np.asarray(directions, dtype=np.float64).reshape(-1, 3),
                    colors=np.asarray(colors, dtype=np.float64).reshape(-1, 3))  # (0, 3) without lights


#: The percentile of the lit head's brightest channel, over its vertices that face the camera, that
#: :func:`auto_exposure` brings down to the exposure target.
EXPOSURE_PERCENTILE = 90.0


def auto_exposure(lighting: Lighting, head: MeshPart, target: float) -> Lighting:
    """The lights dimmed so that the head is not overexposed, as a camera's auto-exposure would.

    The diffuse radiance of the head (the renderer's wrap-Lambert and ambient terms with the part's
    albedo and ambient occlusion, without texture noise or highlights) is evaluated at its vertices
    that face the camera. Where the :data:`EXPOSURE_PERCENTILE` of their brightest channel exceeds
    ``target`` (linear RGB, 1 = white), the ambient and every light are scaled by the same factor to
    bring it to ``target``; darker heads keep their lights (underexposure clips nothing).

    Args:
        lighting: the sampled lights (camera frame).
        head: the head part, with ``colors`` the linear albedo and its pose ``rotation``, ``translation``.
        target: the linear value in ``(0, 1]`` the percentile is brought to.
    """
    if not 0.0 < target <= 1.0:
        raise ValueError(f"target: expected a linear value in (0, 1], got {target}")
    rotation = np.asarray(head.rotation, np.float64)
    position = (head.vertices.astype(np.float64) + np.asarray(head.translation, np.float64)) @ rotation.T
    normal = head.normals.astype(np.float64) @ rotation.T
    facing = np.einsum("ki,ki->k", normal, position) < 0  # towards the camera centre
    if not facing.any():
        return lighting
    normal, albedo = normal[facing], head.colors.astype(np.float64)[facing]
    occlusion = np.ones(len(normal)) if head.occlusion is None else head.occlusion.astype(np.float64)[facing]
    radiance = albedo * occlusion[:, None] * lighting.ambient
    for direction, color in zip(lighting.directions, lighting.colors):
        diffuse = np.maximum((normal @ direction + head.wrap) / (1.0 + head.wrap), 0.0)
        radiance += albedo * (diffuse * (0.5 + 0.5 * occlusion))[:, None] * color
    level = float(np.percentile(radiance.max(1), EXPOSURE_PERCENTILE))
    if level <= target:
        return lighting
    scale = target / level
    return Lighting(ambient=lighting.ambient * scale, directions=lighting.directions, colors=lighting.colors * scale)

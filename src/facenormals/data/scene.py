"""The meshes of one synthetic sample: head, eyeballs, mouth interior, hair or cap, clothing, occluders.

Every builder returns :class:`~facenormals.data.render.MeshPart` objects in the head's model frame
(posed by ``R``, ``t`` like the head) except the occluders, which live in the camera frame.
Segmentation labels (:data:`LABELS`) tell the head surface (skin, eyes, mouth interior: the
surface of the normal map N and the foreground mask) from everything that only occludes it.
"""

from __future__ import annotations

import numpy as np

from facenormals.data.appearance import fourier_noise, srgb_to_linear
from facenormals.data.head import HeadAssets
from facenormals.data.meshes import box_mesh, cylinder_mesh, face_normals, ring_strip, smooth_vertex_normals, sphere_mesh
from facenormals.data.render import MeshPart

__all__ = ["HEAD_LABELS", "LABELS", "clothing_part", "eye_parts", "hair_parts", "mouth_part", "occluder_parts"]

#: Segmentation labels stored with every sample (0 is background).
LABELS = {"background": 0, "skin": 1, "eyes": 2, "mouth": 3, "hair": 4, "headwear": 5, "occluder": 6, "clothing": 7}
#: Labels of the head surface: the pixels where the normal map N is defined (the foreground mask).
HEAD_LABELS = (LABELS["skin"], LABELS["eyes"], LABELS["mouth"])


def _capped_tube_faces(ring_size: int, num_rings: int) -> np.ndarray:
    """Triangles joining ``num_rings`` consecutive rings of ``ring_size`` points, closed by a fan to the
    apex point stored right after them (index ``num_rings * ring_size``)."""
    k = ring_size
    faces = [ring_strip(np.arange(i * k, (i + 1) * k), np.arange((i + 1) * k, (i + 2) * k)) for i in range(num_rings - 1)]
    last = np.arange((num_rings - 1) * k, num_rings * k)
    faces.append(np.stack([last, np.roll(last, -1), np.full(k, num_rings * k)], axis=1))
    return np.concatenate(faces)


def _orient(vertices: np.ndarray, faces: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Flip all faces if their area-weighted normals point against ``direction`` on average."""
    if np.sum(face_normals(vertices, faces) @ direction) < 0:
        return faces[:, ::-1].copy()
    return faces


def _rotation_to(direction: np.ndarray) -> np.ndarray:
    """A rotation taking +z to the unit ``direction``."""
    z = direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    a, b, c, d = q / np.linalg.norm(q)
    return np.array([
        [a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
        [2 * (b * c + a * d), a * a - b * b + c * c - d * d, 2 * (c * d - a * b)],
        [2 * (b * d - a * c), 2 * (c * d + a * b), a * a - b * b - c * c + d * d],
    ])  # fmt: skip


def _fit_sphere(points: np.ndarray, radius: float, start: np.ndarray) -> np.ndarray:
    """Centre of the sphere of given radius nearest to ``points`` (Gauss-Newton from ``start``)."""
    c = start.astype(np.float64)
    for _ in range(8):
        d = points - c
        r = np.linalg.norm(d, axis=1)
        residual = r - radius
        jac = -d / np.maximum(r, 1e-9)[:, None]
        step = np.linalg.lstsq(jac, -residual, rcond=None)[0]
        c = c + step
        if np.linalg.norm(step) < 1e-4:
            break
    return c


def eye_parts(assets: HeadAssets, identity: np.ndarray, vertices: np.ndarray, rng: np.random.Generator,
              iris: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> list[MeshPart]:
    """Eyeballs in the eye openings (fitted to the lid rims of the identity) and dark sockets around them."""
    parts: list[MeshPart] = []
    if not assets.eye_loops:
        return parts
    gaze_yaw, gaze_pitch = np.radians(rng.uniform(-25, 25)), np.radians(rng.uniform(-15, 15))
    gaze = np.array([np.sin(gaze_yaw) * np.cos(gaze_pitch), np.sin(gaze_pitch), -np.cos(gaze_yaw) * np.cos(gaze_pitch)])
    frame = _rotation_to(gaze)
    theta_pupil = rng.uniform(0.13, 0.27)
    sclera = srgb_to_linear(np.array([0.9, 0.86, 0.82]) * rng.uniform(0.8, 1.0))
    sclera_edge = sclera * np.array([0.85, 0.7, 0.68])
    socket_color = srgb_to_linear(np.array([0.55, 0.3, 0.3])) * rng.uniform(0.3, 0.7)
    for loop in assets.eye_loops:
        rim = identity[loop].astype(np.float64)
        radius = 0.5 * (rim[:, 0].max() - rim[:, 0].min()) * rng.uniform(0.95, 1.05)
        center = _fit_sphere(rim, radius, rim.mean(0) + np.array([0.0, 0.0, 0.8 * radius]))
        center[2] += 0.5
        theta_iris = np.arcsin(min(0.95, rng.uniform(5.4, 6.4) / radius))
        angles = np.concatenate([
            [0.0, 0.5 * theta_pupil, theta_pupil, theta_pupil + 0.02],
            theta_pupil + (theta_iris - theta_pupil) * np.array([0.4, 0.75, 0.95]),
            [theta_iris, theta_iris + 0.04], np.linspace(theta_iris + 0.3, np.pi, 8),
        ])  # fmt: skip
        unit, faces, ring = sphere_mesh(angles, 20)
        colors = np.empty((len(unit), 3))
        for k, theta in enumerate(angles):
            if theta < theta_pupil + 0.01:
                c = np.full(3, 0.01)
            elif theta <= theta_iris - 1e-6:
                c = iris * (0.6 + 0.5 * (theta - theta_pupil) / (theta_iris - theta_pupil))
            elif theta <= theta_iris + 0.001:
                c = iris * 0.35
            else:
                c = sclera if theta < 1.3 else sclera_edge
            colors[ring == k] = c
        world = unit @ frame.T
        parts.append(MeshPart(
            vertices=(center + radius * world).astype(np.float32), normals=world.astype(np.float32),
            colors=colors.astype(np.float32), faces=faces, label=2, rotation=rotation, translation=translation,
            specular=0.6, shininess=80.0, wrap=0.0,
        ))  # fmt: skip
        # socket: a cone from the lids to the eyeball's centre, dark pink
        lids = vertices[loop].astype(np.float64)
        middle = lids.mean(0)
        inner = middle + 0.55 * (lids - middle) + np.array([0.0, 0.0, 0.6 * radius])
        points = np.concatenate([lids, inner, center[None]])
        k = len(loop)
        ring0, ring1 = np.arange(k), np.arange(k, 2 * k)
        fan = np.stack([ring1, np.roll(ring1, -1), np.full(k, 2 * k)], axis=1)
        sfaces = _orient(points, np.concatenate([ring_strip(ring0, ring1), fan]), np.array([0.0, 0.0, -1.0]))
        parts.append(MeshPart(
            vertices=points.astype(np.float32), normals=smooth_vertex_normals(points, sfaces),
            colors=np.tile(socket_color, (len(points), 1)).astype(np.float32), faces=sfaces, label=2,
            rotation=rotation, translation=translation, specular=0.3, shininess=30.0,
            occlusion=np.concatenate([np.full(k, 0.6), np.full(k + 1, 0.3)]).astype(np.float32),
        ))  # fmt: skip
    return parts


def mouth_part(assets: HeadAssets, vertices: np.ndarray, rng: np.random.Generator, lip_color: np.ndarray,
               rotation: np.ndarray, translation: np.ndarray) -> list[MeshPart]:
    """A mouth bag behind the lips: inner lips, a row of teeth, and a dark throat."""
    if assets.mouth_loop is None:
        return []
    lips = vertices[assets.mouth_loop].astype(np.float64)
    middle = lips.mean(0)
    half_width = 0.5 * (lips[:, 0].max() - lips[:, 0].min())
    rings = [lips]
    for scale, depth in ((0.93, 3.0), (0.8, 6.0), (0.55, 13.0)):
        rings.append(middle + scale * (lips - middle) + np.array([0.0, 0.0, depth]))
    apex = middle + np.array([0.0, 2.0, 24.0])
    points = np.concatenate(rings + [apex[None]])
    k = len(lips)
    faces = _orient(points, _capped_tube_faces(k, len(rings)), np.array([0.0, 0.0, -1.0]))
    teeth = srgb_to_linear(np.array([0.93, 0.9, 0.8]) * rng.uniform(0.75, 1.0))
    gum = lip_color * 0.6
    throat = srgb_to_linear(np.array([0.25, 0.05, 0.05])) * rng.uniform(0.3, 0.8)
    colors = np.empty((len(points), 3))
    colors[:k] = lip_color
    colors[k:2 * k] = lip_color * 0.8
    tooth = np.abs(rings[2][:, 0] - middle[0]) < rng.uniform(0.55, 0.8) * half_width
    colors[2 * k:3 * k] = np.where(tooth[:, None], teeth[None], gum[None])
    colors[3 * k:4 * k] = throat
    colors[4 * k] = throat * 0.5
    occlusion = np.concatenate([np.full(k, 0.8), np.full(k, 0.6), np.full(k, 0.5), np.full(k + 1, 0.2)])
    return [MeshPart(
        vertices=points.astype(np.float32), normals=smooth_vertex_normals(points, faces),
        colors=colors.astype(np.float32), faces=faces, label=3, rotation=rotation, translation=translation,
        occlusion=occlusion.astype(np.float32), specular=0.3, shininess=40.0,
    )]  # fmt: skip


def clothing_part(assets: HeadAssets, vertices: np.ndarray, rng: np.random.Generator,
                  rotation: np.ndarray, translation: np.ndarray) -> list[MeshPart]:
    """Collar and shoulders continuing the neck cut downwards (closes the neck opening)."""
    if assets.neck_loop is None:
        return []
    neck = vertices[assets.neck_loop].astype(np.float64)
    middle = neck.mean(0)
    wide_x, wide_z = rng.uniform(2.0, 3.0), rng.uniform(1.2, 1.7)
    rings = [neck]
    for sx, sz, dy in ((1.08, 1.08, 12.0), (wide_x, wide_z, rng.uniform(50, 90)), (1.1 * wide_x, 1.1 * wide_z, 260.0)):
        rings.append(middle + (neck - middle) * np.array([sx, 1.0, sz]) + np.array([0.0, dy, 0.0]))
    bottom = middle + np.array([0.0, 260.0, 0.0])
    points = np.concatenate(rings + [bottom[None]])
    k = len(neck)
    faces = _capped_tube_faces(k, len(rings))
    outward = np.sum(face_normals(points, faces) * (points[faces].mean(1) - middle) * np.array([1.0, 0.0, 1.0]))
    if outward < 0:
        faces = faces[:, ::-1].copy()
    hsv_value = rng.uniform(0.1, 0.95)
    base = srgb_to_linear(np.clip(rng.uniform(0, 1, size=3) * rng.uniform(0.2, 1.0) + hsv_value * 0.3, 0, 1))
    colors = np.tile(base, (len(points), 1)) * (1.0 + 0.15 * fourier_noise(points, rng, 40.0))[:, None]
    return [MeshPart(
        vertices=points.astype(np.float32), normals=smooth_vertex_normals(points, faces),
        colors=np.clip(colors, 0, 1).astype(np.float32), faces=faces, label=7, rotation=rotation,
        translation=translation, specular=rng.uniform(0.0, 0.15), shininess=10.0, wrap=0.1,
        noise=(rng.uniform(0.05, 0.3), rng.uniform(0.1, 0.6), rng.uniform(0.2, 5.0), rng.uniform(0, 100)),
    )]  # fmt: skip


def _hair_field(assets: HeadAssets, rng: np.random.Generator, front: float, side: float, back: float) -> np.ndarray:
    """Signed height (mm) above a random hairline through ``front``/``side``/``back`` heights."""
    phi = np.abs(assets.azimuth.astype(np.float64))
    to_side = np.clip((phi - 0.35) / (np.pi / 2 - 0.35), 0.0, 1.0)
    to_back = np.clip((phi - np.pi / 2) / (np.pi / 2), 0.0, 1.0)
    ease = lambda t: t * t * (3 - 2 * t)  # noqa: E731
    line = np.where(phi < np.pi / 2, front + (side - front) * ease(to_side), side + (back - side) * ease(to_back))
    waves = rng.integers(4, 14)
    line += rng.uniform(1.0, 6.0) * np.sin(waves * assets.azimuth + rng.uniform(0, 2 * np.pi))
    line += rng.uniform(0.5, 3.0) * np.sin(rng.integers(15, 30) * assets.azimuth + rng.uniform(0, 2 * np.pi))
    return assets.height - line


def hair_parts(assets: HeadAssets, vertices: np.ndarray, normals: np.ndarray, rng: np.random.Generator,
               hair_color: np.ndarray, style: str, rotation: np.ndarray, translation: np.ndarray) -> list[MeshPart]:
    """Procedural hair (``style="hair"``) or a cap (``style="cap"``) as a shell around the skull.

    The shell lies at ``h`` mm outside a smoothed copy of the head (its radial distance from the
    skull centre smoothed over the mesh, so that it passes over the ears), on the vertices above a
    random hairline; ``h`` tapers to 0.5 mm at the hairline so that the edge meets the skin. The
    shell is shaded with the head's vertex normals (``normals``).
    """
    v = vertices.astype(np.float64)
    mean = assets.model.mean.detach().cpu().numpy()
    center = assets.skull_center + (v - mean).mean(0)
    rel = v - center
    radius = np.linalg.norm(rel, axis=1)
    direction = rel / np.maximum(radius, 1e-9)[:, None]
    # the smoothed radius of the mean head, plus this head's (already smooth) deviation from it
    deviation = radius - np.linalg.norm(mean - assets.skull_center, axis=1)
    for _ in range(4):
        deviation = assets.smoothing @ deviation
    smooth = np.maximum(assets.skull_radius + deviation, radius - 4.0)  # never sink more than 4 mm into a bump
    height = assets.height.astype(np.float64)
    parts: list[MeshPart] = []
    if style == "hair":
        bangs = rng.random() < 0.25
        front = rng.uniform(5.0, 35.0) if bangs else rng.uniform(50.0, 100.0)
        side = rng.uniform(-75.0, 20.0)
        back = min(side - 10.0, rng.uniform(-170.0, -40.0))
        s = _hair_field(assets, rng, front, side, back)
        base = rng.uniform(2.0, 12.0)
        thickness = 0.5 + base * np.clip(s / 12.0, 0.0, 1.0)
        thickness += rng.uniform(0.0, 25.0) * np.clip((height - 40.0) / 70.0, 0.0, 1.0)
        thickness += rng.uniform(0.0, 30.0) * np.clip((-20.0 - height) / 60.0, 0.0, 1.0) * np.clip(s / 20.0, 0, 1)
        thickness *= 1.0 + 0.2 * assets.noise(rng, "hair_volume")
        label, specular, shininess, wrap = 4, rng.uniform(0.1, 0.35), rng.uniform(15.0, 40.0), 0.2
        noise = (rng.uniform(0.15, 0.4), rng.uniform(0.3, 1.0), rng.uniform(0.05, 0.2), rng.uniform(0, 100))
    elif style == "cap":
        line = rng.uniform(35.0, 75.0) + rng.uniform(-15.0, 10.0) * np.cos(assets.azimuth.astype(np.float64))
        s = height - line
        thickness = np.full(len(v), rng.uniform(3.0, 7.0)) + 2.0 * np.clip(s / 10.0, 0.0, 1.0)
        label, specular, shininess, wrap = 5, rng.uniform(0.0, 0.2), 12.0, 0.1
        noise = (rng.uniform(0.05, 0.25), rng.uniform(0.2, 1.0), 1.0, rng.uniform(0, 100))
    else:
        raise ValueError(f"style: expected 'hair' or 'cap', got {style!r}")
    inside = s > 0.0
    keep = inside[assets.faces].all(axis=1)
    if keep.sum() < 10:
        return parts
    faces = assets.faces[keep]
    used = np.unique(faces)
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    faces = remap[faces]
    shell = center + direction[used] * (smooth[used] + thickness[used])[:, None]
    if style == "hair":
        # strands: stripes across the azimuth, slow along the height, darker towards the roots
        stripes = assets.noise(rng, "strands")[used]
        depth = np.clip(s[used] / 30.0, 0.0, 1.0)
        colors = hair_color[None] * (1.0 + 0.3 * stripes[:, None]) * (0.8 + 0.2 * depth[:, None])
        occlusion = np.clip(0.55 + 0.45 * np.clip(thickness[used] / 6.0, 0, 1), 0, 1)
    else:
        colors = np.tile(hair_color, (len(used), 1))
        occlusion = np.ones(len(used))
    parts.append(MeshPart(
        vertices=shell.astype(np.float32), normals=normals[used].astype(np.float32),
        colors=np.clip(colors, 0, 1).astype(np.float32), faces=faces, label=label, rotation=rotation,
        translation=translation, occlusion=occlusion.astype(np.float32), specular=specular,
        shininess=shininess, wrap=wrap, noise=noise,
    ))  # fmt: skip
    if style == "cap" and rng.random() < 0.7:
        parts.append(_brim(shell, assets.azimuth[used], center, rng, hair_color, rotation, translation))
    return parts


def _brim(shell: np.ndarray, azimuth: np.ndarray, center: np.ndarray, rng: np.random.Generator,
          color: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> MeshPart:
    """A cap's visor: a drooping half-annulus in front of the lowest front edge of the cap."""
    front = np.abs(azimuth) < 0.6
    low = shell[front][:, 1].max() if front.any() else shell[:, 1].max()
    band = np.abs(shell[:, 1] - low) < 10.0
    ax = np.abs(shell[band, 0] - center[0]).max()
    az = -(shell[band, 2] - center[2]).min()
    angles = np.linspace(-1.25, 1.25, 21)
    length, droop = rng.uniform(45.0, 75.0), np.radians(rng.uniform(5.0, 25.0))
    inner = np.stack([center[0] + ax * np.sin(angles), np.full_like(angles, low - 2.0), center[2] - az * np.cos(angles)], 1)
    out = np.stack([np.sin(angles) * 0.6, np.zeros_like(angles), -np.cos(angles)], 1)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    outer = inner + length * np.cos(droop) * out + np.array([0.0, length * np.sin(droop), 0.0])
    points = np.concatenate([inner, outer])
    n = len(angles)
    faces = _orient(points, ring_strip(np.arange(n), np.arange(n, 2 * n), closed=False), np.array([0.0, -1.0, 0.0]))
    return MeshPart(
        vertices=points.astype(np.float32), normals=smooth_vertex_normals(points, faces),
        colors=np.tile(color * rng.uniform(0.7, 1.1), (len(points), 1)).astype(np.float32), faces=faces, label=5,
        rotation=rotation, translation=translation, specular=0.1, shininess=10.0,
    )  # fmt: skip


def occluder_parts(rng: np.random.Generator, targets: np.ndarray, head_size: float, skin: np.ndarray,
                   count: int) -> list[MeshPart]:
    """``count`` random solids (ellipsoid, box, cylinder) between the camera and the face.

    Args:
        targets: ``(M, 3)`` camera-frame points on the face to cover partially (e.g. landmarks).
        head_size: head size in mm, to scale the solids.
        skin: a linear-RGB skin colour for hand-like blobs.
        count: number of solids.
    """
    parts = []
    for _ in range(count):
        target = targets[rng.integers(len(targets))]
        depth = max(target[2] - rng.uniform(0.1, 0.6) * head_size, 0.4 * target[2])
        # size relative to the head as seen in the image: 5-18 % of its size per half-axis
        size = head_size * rng.uniform(0.05, 0.18) * rng.uniform(0.6, 1.4, size=3) * depth / target[2]
        offset = rng.normal(size=2) * 0.6 * size[:2]
        position = np.array([target[0] * depth / target[2] + offset[0], target[1] * depth / target[2] + offset[1], depth])
        kind = rng.choice(["ellipsoid", "box", "cylinder"], p=[0.45, 0.3, 0.25])
        if kind == "ellipsoid":
            unit, faces, _ = sphere_mesh(np.linspace(0.0, np.pi, 12), 18)
            normals = unit / size
        elif kind == "box":
            unit, faces, normals = box_mesh()
            normals = normals / size
        else:
            unit, faces, normals = cylinder_mesh(18)
            normals = normals / size
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        rot = _random_rotation(rng)
        if kind == "ellipsoid" and rng.random() < 0.5:
            base = skin * rng.uniform(0.8, 1.1)
        else:
            base = srgb_to_linear(rng.uniform(0.05, 0.95, size=3))
        parts.append(MeshPart(
            vertices=((unit * size) @ rot.T + position).astype(np.float32), normals=(normals @ rot.T).astype(np.float32),
            colors=np.tile(np.clip(base, 0, 1), (len(unit), 1)).astype(np.float32), faces=faces, label=6,
            rotation=np.eye(3), translation=np.zeros(3), specular=rng.uniform(0.0, 0.5), shininess=rng.uniform(5, 60),
            noise=(rng.uniform(0.0, 0.4), rng.uniform(0.02, 0.3), rng.uniform(0.3, 3.0), rng.uniform(0, 100)),
        ))  # fmt: skip
    return parts

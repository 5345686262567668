r"""A tiled offscreen OpenGL renderer for training samples: shaded colour, exact normals and depth.

Every sample is drawn into its own tile of one large framebuffer, and the whole batch is read back
at once (on a software rasteriser such as Mesa's llvmpipe the per-render fixed costs dominate at
128×128). One pass writes two render targets:

- ``RGBA8``: the shaded sRGB colour and, in alpha, the segmentation label of the surface;
- ``RGBA32F``: the camera-frame unit normal and the camera-frame depth :math:`z` (float32).

Geometry is posed in the vertex shader by the library's own projection
:math:`a = \frac{1}{z} K R (p + t)` (``docs/conventions.md``), written straight into clip
coordinates with :math:`w = z`: there is no OpenGL camera (no −z view axis, no y-up flip), and
the camera-frame normal is :math:`R n`. Pixel ``(u, v)`` has its centre at window coordinate
``(u + ½, v + ½)``; framebuffer row ``v`` is read back as image row ``v``.

Colour is supersampled ``s × s`` (``s`` odd): the low-resolution pixel is the mean of its ``s²``
samples (premultiplied by coverage, for compositing over a background), and the centre sample of each block lies exactly at the pixel centre
``(s u + (s-1)/2, s v + (s-1)/2)``, so normals, depth and labels are point samples at pixel
centres, as in :func:`~facenormals.render.rasterize_triangles`.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass, field

import numpy as np

from facenormals.core.check import check_positive

__all__ = ["Lighting", "MeshPart", "RenderedTiles", "TileRenderer", "TileScene"]

NEAR_MM = 5.0
"""The default near clipping depth of :class:`TileRenderer`, mm."""
FAR_MM = 50000.0
"""The default far clipping depth of :class:`TileRenderer`, mm."""

#: Most directional lights in a scene (the size of the shader's light arrays).
MAX_LIGHTS = 3
#: Largest side of the supersampled framebuffer (24 bytes a sample: 400 MB at 4096²).
MAX_FRAMEBUFFER = 4096

_VERTEX_SHADER = """
#version 330 core
layout(location = 0) in vec3 a_position;
layout(location = 1) in vec3 a_normal;
layout(location = 2) in vec4 a_color;
uniform mat3 u_rotation;
uniform vec3 u_translation;
uniform vec4 u_projection;  // (2f/W, 2f/H, 2(u0+1/2)/W - 1, 2(v0+1/2)/H - 1)
uniform vec2 u_clip;        // near, far (mm)
out vec3 v_camera;
out vec3 v_normal;
out vec4 v_color;
out vec3 v_object;
void main() {
    vec3 X = u_rotation * (a_position + u_translation);
    v_camera = X;
    v_normal = u_rotation * a_normal;
    v_color = a_color;
    v_object = a_position;
    float n = u_clip.x, f = u_clip.y;
    gl_Position = vec4(u_projection.x * X.x + u_projection.z * X.z,
                       u_projection.y * X.y + u_projection.w * X.z,
                       (X.z * (f + n) - 2.0 * f * n) / (f - n), X.z);
}
"""

_FRAGMENT_SHADER = """
#version 330 core
in vec3 v_camera;
in vec3 v_normal;
in vec4 v_color;
in vec3 v_object;
layout(location = 0) out vec4 o_color;
layout(location = 1) out vec4 o_geometry;
uniform int u_label;
uniform vec3 u_ambient;
uniform int u_num_lights;
uniform vec3 u_light_direction[3];
uniform vec3 u_light_color[3];
uniform vec3 u_material;    // specular strength, shininess, wrap (soft diffuse falloff)
uniform vec4 u_noise;       // amplitude, frequency (1/mm), stretch along object y, seed
float hash(vec3 p) {
    p = fract(p * vec3(0.1031, 0.1030, 0.0973));
    p += dot(p, p.yxz + 33.33);
    return fract((p.x + p.y) * p.z);
}
float value_noise(vec3 p) {
    vec3 i = floor(p);
    vec3 f = fract(p);
    f = f * f * (3.0 - 2.0 * f);
    float a = mix(mix(hash(i), hash(i + vec3(1, 0, 0)), f.x), mix(hash(i + vec3(0, 1, 0)), hash(i + vec3(1, 1, 0)), f.x), f.y);
    float b = mix(mix(hash(i + vec3(0, 0, 1)), hash(i + vec3(1, 0, 1)), f.x), mix(hash(i + vec3(0, 1, 1)), hash(i + vec3(1, 1, 1)), f.x), f.y);
    return mix(a, b, f.z);
}
void main() {
    vec3 n = normalize(v_normal);
    vec3 to_eye = normalize(-v_camera);
    vec3 s = dot(n, to_eye) < 0.0 ? -n : n;  // two-sided shading
    vec3 albedo = v_color.rgb;
    if (u_noise.x > 0.0) {
        vec3 q = v_object * u_noise.y * vec3(1.0, u_noise.z, 1.0) + u_noise.w;
        float t = 0.65 * value_noise(q) + 0.35 * value_noise(2.7 * q + 17.0);
        albedo *= 1.0 + u_noise.x * (2.0 * t - 1.0);
    }
    vec3 c = albedo * u_ambient * v_color.a;
    for (int k = 0; k < u_num_lights; ++k) {
        vec3 l = u_light_direction[k];
        float cosine = dot(s, l);
        float diffuse = max((cosine + u_material.z) / (1.0 + u_material.z), 0.0);
        vec3 h = normalize(l + to_eye);
        float specular = cosine > 0.0 ? u_material.x * pow(max(dot(s, h), 0.0), u_material.y) : 0.0;
        c += (albedo * diffuse * mix(1.0, v_color.a, 0.5) + specular) * u_light_color[k];
    }
    c = pow(clamp(c, 0.0, 1.0), vec3(1.0 / 2.2));
    o_color = vec4(c, float(u_label) / 255.0);
    o_geometry = vec4(n, v_camera.z);
}
"""


@dataclass
class MeshPart:
    """One mesh of a scene with its pose, material and segmentation label.

    Attributes:
        vertices: ``(N, 3)`` positions in the part's frame (mm).
        normals: ``(N, 3)`` unit normals in the part's frame.
        colors: ``(N, 3)`` linear-RGB albedo in ``[0, 1]``.
        faces: ``(F, 3)`` triangles.
        label: segmentation label written with every pixel of the part (1..255).
        rotation: ``(3, 3)`` and translation ``(3,)``: camera point ``X_c = R (p + t)``.
        occlusion: ``(N,)`` ambient occlusion in ``[0, 1]`` (1 = open), or ``None``.
        specular, shininess, wrap: Blinn-Phong strength and exponent, and the diffuse wrap that
            softens the terminator (skin-like).
        noise: procedural albedo texture ``(amplitude, frequency per mm, stretch along y, seed)``.
    """

    vertices: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    faces: np.ndarray
    label: int
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    occlusion: np.ndarray | None = None
    specular: float = 0.1
    shininess: float = 20.0
    wrap: float = 0.0
    noise: tuple[float, float, float, float] = (0.0, 0.1, 1.0, 0.0)


@dataclass
class Lighting:
    """Ambient light plus up to three directional lights (linear RGB, camera frame).

    Attributes:
        ambient: ``(3,)`` ambient radiance.
        directions: ``(L, 3)`` unit vectors from the surface towards each light, camera frame.
        colors: ``(L, 3)`` light radiances.
    """

    ambient: np.ndarray
    directions: np.ndarray
    colors: np.ndarray


@dataclass
class TileScene:
    """Everything drawn into one tile: parts, intrinsics ``(f, u0, v0)`` and lighting."""

    parts: list[MeshPart]
    intrinsics: np.ndarray
    lighting: Lighting


@dataclass
class RenderedTiles:
    """Read-back tiles, in the order of the scenes given to :meth:`TileRenderer.render`.

    Attributes:
        color: ``(B, H, W, 3)`` uint8 shaded colour, premultiplied by coverage (0 on background):
            the mean of the ``s²`` supersamples with background samples counted as black.
        coverage: ``(B, H, W)`` uint8 fraction of covered supersamples, 0..255. Composite over a
            background ``bg`` as ``color + bg · (1 - coverage / 255)``.
        normals: ``(B, H, W, 3)`` float32 camera-frame unit normals at pixel centres, 0 on background.
        depth: ``(B, H, W)`` float32 camera-frame depth at pixel centres, ``inf`` on background.
        labels: ``(B, H, W)`` uint8 labels at pixel centres, 0 on background.
    """

    color: np.ndarray
    coverage: np.ndarray
    normals: np.ndarray
    depth: np.ndarray
    labels: np.ndarray


class TileRenderer:
    """Render batches of scenes into the tiles of one offscreen framebuffer.

    Creating the renderer selects the headless platform (:func:`~facenormals.data.select_gl_platform`)
    and creates its own OpenGL context. A process may hold several renderers; each makes its
    context current before drawing.

    Args:
        image_size: ``(H, W)`` of one sample.
        grid: tiles per side; a batch holds at most ``grid²`` scenes. Lowered when the framebuffer
            would exceed :data:`MAX_FRAMEBUFFER` or the OpenGL implementation's limit.
        supersample: odd colour supersampling factor ``s``.
        near: near clipping depth in mm.
        far: far clipping depth in mm.

    Raises:
        HeadlessGLError: if no headless OpenGL platform can be used.
        ValueError: on a bad size, grid, supersampling factor or clipping planes (``0 < near < far``,
            finite).
    """

    def __init__(
        self,
        image_size: tuple[int, int] = (128, 128),
        grid: int = 8,
        supersample: int = 3,
        near: float = NEAR_MM,
        far: float = FAR_MM,
    ) -> None:
        from facenormals.data.gl_platform import create_gl_context

        height, width = (int(s) for s in image_size)
        if height < 1 or width < 1:
            raise ValueError(f"image_size: expected positive (H, W), got {image_size}")
        if grid < 1:
            raise ValueError(f"grid: expected >= 1, got {grid}")
        if supersample < 1 or supersample % 2 == 0:
            raise ValueError(f"supersample: expected an odd factor >= 1, got {supersample}")
        self.image_size = (height, width)
        self.grid = int(grid)
        self.supersample = int(supersample)
        self.near = check_positive(near, "near")  # the projection assumes 0 < near < far, both finite
        self.far = check_positive(far, "far")
        if not self.far > self.near:
            raise ValueError(f"far: expected a clipping distance beyond near = {self.near:g} mm, got {self.far:g}")
        self._context = create_gl_context()
        try:
            self._setup()
        except BaseException:
            self.close()  # a failed setup must not leak the context
            raise

    @property
    def capacity(self) -> int:
        """Scenes per batch, ``grid²``."""
        return self.grid * self.grid

    def __repr__(self) -> str:
        return (
            f"TileRenderer(image_size={self.image_size}, grid={self.grid}, supersample={self.supersample}, "
            f"platform={self._context.platform_name!r})"
        )

    # ------------------------------------------------------------------ setup

    def _setup(self) -> None:
        from OpenGL import GL as gl

        self._gl = gl
        program = gl.glCreateProgram()
        for source, kind in ((_VERTEX_SHADER, gl.GL_VERTEX_SHADER), (_FRAGMENT_SHADER, gl.GL_FRAGMENT_SHADER)):
            shader = gl.glCreateShader(kind)
            gl.glShaderSource(shader, source)
            gl.glCompileShader(shader)
            if not gl.glGetShaderiv(shader, gl.GL_COMPILE_STATUS):
                raise RuntimeError(f"shader compilation failed: {gl.glGetShaderInfoLog(shader)}")
            gl.glAttachShader(program, shader)
        gl.glLinkProgram(program)
        if not gl.glGetProgramiv(program, gl.GL_LINK_STATUS):
            raise RuntimeError(f"shader link failed: {gl.glGetProgramInfoLog(program)}")
        self._program = program
        names = ["u_rotation", "u_translation", "u_projection", "u_clip", "u_label", "u_ambient",
                 "u_num_lights", "u_light_direction", "u_light_color", "u_material", "u_noise"]
        self._uniform = {name: gl.glGetUniformLocation(program, name) for name in names}

        h, w, s = self.image_size[0], self.image_size[1], self.supersample
        limit = min(int(gl.glGetIntegerv(gl.GL_MAX_RENDERBUFFER_SIZE)), int(np.min(gl.glGetIntegerv(gl.GL_MAX_VIEWPORT_DIMS))),
                    MAX_FRAMEBUFFER)
        if max(h, w) * s > limit:
            raise ValueError(f"image_size x supersample = {max(h, w) * s} exceeds the renderer's limit of {limit} pixels")
        self.grid = g = min(self.grid, limit // (max(h, w) * s))  # fewer tiles when the framebuffer would be too large
        self._hi_size = (g * h * s, g * w * s)
        self._lo_size = (g * h, g * w)
        self._fbo_hi = gl.glGenFramebuffers(1)
        self._fbo_lo = gl.glGenFramebuffers(1)
        buffers = gl.glGenRenderbuffers(4)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fbo_hi)
        for buffer, fmt, attachment in (
            (buffers[0], gl.GL_RGBA8, gl.GL_COLOR_ATTACHMENT0),
            (buffers[1], gl.GL_RGBA32F, gl.GL_COLOR_ATTACHMENT1),
            (buffers[2], gl.GL_DEPTH_COMPONENT32F, gl.GL_DEPTH_ATTACHMENT),
        ):
            gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, buffer)
            gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, fmt, self._hi_size[1], self._hi_size[0])
            gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, attachment, gl.GL_RENDERBUFFER, buffer)
        self._check_framebuffer("supersampled")
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fbo_lo)
        gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, buffers[3])
        gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, gl.GL_RGBA32F, self._lo_size[1], self._lo_size[0])
        gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_COLOR_ATTACHMENT0, gl.GL_RENDERBUFFER, buffers[3])
        self._check_framebuffer("pixel-centre")
        self._vao = gl.glGenVertexArrays(1)
        self._vbo, self._ebo = gl.glGenBuffers(2)
        gl.glBindVertexArray(self._vao)
        gl.glBindBuffer(gl.GL_ARRAY_BUFFER, self._vbo)
        gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, self._ebo)
        stride = 10 * 4
        for location, (size, offset) in enumerate(((3, 0), (3, 12), (4, 24))):
            gl.glEnableVertexAttribArray(location)
            gl.glVertexAttribPointer(location, size, gl.GL_FLOAT, False, stride, ctypes.c_void_p(offset))
        gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 1)

    def _check_framebuffer(self, name: str) -> None:
        gl = self._gl
        status = gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER)
        if status != gl.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"the {name} framebuffer is incomplete (status {status:#x})")

    # ------------------------------------------------------------------ render

    def render(self, scenes: list[TileScene], tiles: list[int] | None = None) -> RenderedTiles:
        """Render up to ``grid²`` scenes in one pass and read them back.

        Args:
            scenes: the scenes.
            tiles: the tile of each scene, distinct, in ``[0, grid²)`` (default ``0, 1, ...``). A
                scene always drawn in the same tile gives bit-identical pixels whatever else is
                in the batch.

        Returns:
            The :class:`RenderedTiles`, in the order of ``scenes``.

        Raises:
            ValueError: on bad tiles, a part whose arrays do not have the shapes of :class:`MeshPart`
                or whose faces index outside its vertices, non-finite arrays, intrinsics that are not
                ``(3,)`` or whose focal length is not positive, or lighting with more than
                :data:`MAX_LIGHTS` lights.
            RuntimeError: after :meth:`close`.
        """
        if self._context is None:
            raise RuntimeError("TileRenderer: render() after close(); create a new renderer")
        gl = self._gl
        if tiles is None:
            tiles = list(range(len(scenes)))
        tiles = [int(t) for t in tiles]
        if len(tiles) != len(scenes):
            raise ValueError(f"tiles: expected {len(scenes)} tiles, got {len(tiles)}")
        if len(set(tiles)) != len(tiles) or any(not 0 <= t < self.capacity for t in tiles):
            raise ValueError(f"tiles: expected distinct tiles in [0, {self.capacity}), got {tiles}")
        for k, scene in enumerate(scenes):
            _check_scene(scene, f"scenes[{k}]")
        self._context.make_current()
        vertex_data, index_data, draws = self._pack(scenes)
        gl.glBindVertexArray(self._vao)
        gl.glBindBuffer(gl.GL_ARRAY_BUFFER, self._vbo)
        gl.glBufferData(gl.GL_ARRAY_BUFFER, vertex_data.nbytes, ctypes.c_void_p(vertex_data.ctypes.data), gl.GL_STREAM_DRAW)
        gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, self._ebo)
        gl.glBufferData(gl.GL_ELEMENT_ARRAY_BUFFER, index_data.nbytes, ctypes.c_void_p(index_data.ctypes.data),
                        gl.GL_STREAM_DRAW)

        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fbo_hi)
        gl.glDrawBuffers(2, [gl.GL_COLOR_ATTACHMENT0, gl.GL_COLOR_ATTACHMENT1])
        gl.glDisable(gl.GL_SCISSOR_TEST)
        gl.glDisable(gl.GL_BLEND)
        gl.glDisable(gl.GL_CULL_FACE)
        gl.glEnable(gl.GL_DEPTH_TEST)
        gl.glDepthFunc(gl.GL_LESS)
        gl.glViewport(0, 0, self._hi_size[1], self._hi_size[0])
        gl.glClearBufferfv(gl.GL_COLOR, 0, np.zeros(4, np.float32))
        gl.glClearBufferfv(gl.GL_COLOR, 1, np.zeros(4, np.float32))
        gl.glClearBufferfv(gl.GL_DEPTH, 0, np.ones(1, np.float32))
        gl.glEnable(gl.GL_SCISSOR_TEST)
        gl.glUseProgram(self._program)
        u = self._uniform
        gl.glUniform2f(u["u_clip"], self.near, self.far)
        h, w, s = self.image_size[0], self.image_size[1], self.supersample
        for scene, tile, scene_draws in zip(scenes, tiles, draws):
            x0, y0 = (tile % self.grid) * w * s, (tile // self.grid) * h * s
            gl.glViewport(x0, y0, w * s, h * s)
            gl.glScissor(x0, y0, w * s, h * s)
            f, u0, v0 = (float(x) for x in scene.intrinsics)
            gl.glUniform4f(u["u_projection"], 2 * f / w, 2 * f / h, 2 * (u0 + 0.5) / w - 1, 2 * (v0 + 0.5) / h - 1)
            light = scene.lighting
            count = len(light.directions)
            gl.glUniform3f(u["u_ambient"], *(float(x) for x in light.ambient))
            gl.glUniform1i(u["u_num_lights"], count)
            if count:
                gl.glUniform3fv(u["u_light_direction"], count, np.ascontiguousarray(light.directions[:count], np.float32))
                gl.glUniform3fv(u["u_light_color"], count, np.ascontiguousarray(light.colors[:count], np.float32))
            for part, (index_offset, index_count, base_vertex) in zip(scene.parts, scene_draws):
                if index_count == 0:
                    continue
                gl.glUniformMatrix3fv(u["u_rotation"], 1, True, np.ascontiguousarray(part.rotation, np.float32))
                gl.glUniform3f(u["u_translation"], *(float(x) for x in part.translation))
                gl.glUniform1i(u["u_label"], int(part.label))
                gl.glUniform3f(u["u_material"], float(part.specular), float(part.shininess), float(part.wrap))
                gl.glUniform4f(u["u_noise"], *(float(x) for x in part.noise))
                gl.glDrawElementsBaseVertex(
                    gl.GL_TRIANGLES, index_count, gl.GL_UNSIGNED_INT, ctypes.c_void_p(4 * index_offset), base_vertex
                )
        gl.glDisable(gl.GL_SCISSOR_TEST)
        return self._read(tiles)

    def _pack(self, scenes: list[TileScene]) -> tuple[np.ndarray, np.ndarray, list[list[tuple[int, int, int]]]]:
        """Interleave all parts into one vertex array ``(V, 10)`` and one index array."""
        vertex_blocks, index_blocks, draws = [], [], []
        vertex_count = index_count = 0
        for scene in scenes:
            scene_draws = []
            for part in scene.parts:
                n = len(part.vertices)
                block = np.empty((n, 10), dtype=np.float32)
                block[:, 0:3] = part.vertices
                block[:, 3:6] = part.normals
                block[:, 6:9] = part.colors
                block[:, 9] = 1.0 if part.occlusion is None else part.occlusion
                faces = part.faces.ravel() if part.faces.dtype == np.uint32 else part.faces.astype(np.uint32).ravel()
                vertex_blocks.append(block)
                index_blocks.append(faces)
                scene_draws.append((index_count, faces.size, vertex_count))
                vertex_count += n
                index_count += faces.size
            draws.append(scene_draws)
        vertices = np.concatenate(vertex_blocks) if vertex_blocks else np.zeros((0, 10), np.float32)
        indices = np.concatenate(index_blocks) if index_blocks else np.zeros(0, np.uint32)
        return vertices, indices, draws

    def _read(self, tiles: list[int]) -> RenderedTiles:
        import cv2

        gl = self._gl
        h, w, s, g = self.image_size[0], self.image_size[1], self.supersample, self.grid
        rows = [t // g for t in tiles]
        r0, r1 = (min(rows), max(rows) + 1) if rows else (0, 0)
        # colour: all supersamples of the used tile rows, box-filtered to pixels (premultiplied)
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, self._fbo_hi)
        gl.glReadBuffer(gl.GL_COLOR_ATTACHMENT0)
        hi_w = self._hi_size[1]
        raw = gl.glReadPixels(0, r0 * h * s, hi_w, (r1 - r0) * h * s, gl.GL_RGBA, gl.GL_UNSIGNED_BYTE)
        hi = np.frombuffer(raw, dtype=np.uint8).reshape((r1 - r0) * h * s, hi_w, 4)
        labels = hi[(s - 1) // 2::s, (s - 1) // 2::s, 3]
        if s > 1:
            hi = hi.copy()
            hi[..., 3] = np.where(hi[..., 3] > 0, np.uint8(255), np.uint8(0))
            lo = cv2.resize(hi, (hi_w // s, (r1 - r0) * h), interpolation=cv2.INTER_AREA)
        else:
            lo = hi.copy()
            lo[..., 3] = np.where(lo[..., 3] > 0, np.uint8(255), np.uint8(0))
        # normals and depth: the centre sample of each s x s block, picked by a nearest-neighbour blit
        gl.glReadBuffer(gl.GL_COLOR_ATTACHMENT1)
        gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, self._fbo_lo)
        gl.glDrawBuffers(1, [gl.GL_COLOR_ATTACHMENT0])
        gl.glBlitFramebuffer(0, 0, self._hi_size[1], self._hi_size[0], 0, 0, self._lo_size[1], self._lo_size[0],
                             gl.GL_COLOR_BUFFER_BIT, gl.GL_NEAREST)
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, self._fbo_lo)
        gl.glReadBuffer(gl.GL_COLOR_ATTACHMENT0)
        raw = gl.glReadPixels(0, r0 * h, self._lo_size[1], (r1 - r0) * h, gl.GL_RGBA, gl.GL_FLOAT)
        geometry = np.asarray(raw, dtype=np.float32).reshape((r1 - r0) * h, self._lo_size[1], 4)

        def tiles_of(image: np.ndarray) -> np.ndarray:
            out = np.empty((len(tiles), h, w) + image.shape[2:], dtype=image.dtype)
            for k, tile in enumerate(tiles):
                ty, tx = tile // g - r0, tile % g
                out[k] = image[ty * h:(ty + 1) * h, tx * w:(tx + 1) * w]
            return out

        label = tiles_of(labels)
        geo = tiles_of(geometry)
        color = tiles_of(lo)
        foreground = label > 0
        return RenderedTiles(
            color=np.ascontiguousarray(color[..., :3]),
            coverage=np.ascontiguousarray(color[..., 3]),
            normals=np.where(foreground[..., None], geo[..., :3], np.float32(0.0)),
            depth=np.where(foreground, geo[..., 3], np.float32(np.inf)),
            labels=label,
        )

    def close(self) -> None:
        """Release the OpenGL context."""
        if getattr(self, "_context", None) is not None:
            self._context.delete()
            self._context = None


def _check_shape(array: object, shape: tuple[int | None, ...], name: str) -> None:
    """Raise ``ValueError`` unless ``array`` has ``shape`` (``None``: any size, shown as N)."""
    got = np.shape(array)
    if len(got) != len(shape) or any(want is not None and want != size for want, size in zip(shape, got)):
        expected = ", ".join("N" if want is None else str(want) for want in shape) + ("," if len(shape) == 1 else "")
        raise ValueError(f"{name}: expected shape ({expected}), got {got}")


def _check_finite(array: object, name: str) -> None:
    """Raise ``ValueError`` unless ``array`` holds finite numbers only (NaN draws garbage or nothing)."""
    values = np.asarray(array)
    if values.dtype.kind not in "iuf" or not np.isfinite(values).all():
        raise ValueError(f"{name}: expected finite numbers, got " +
                         (f"dtype {values.dtype}" if values.dtype.kind not in "iuf" else "NaN or infinite values"))


def _check_scene(scene: TileScene, name: str) -> None:
    """Raise ``ValueError`` naming the first array of ``scene`` that does not fit (the GPU would read
    outside its buffers on an out-of-range face or a short array)."""
    _check_shape(scene.intrinsics, (3,), f"{name}.intrinsics")
    _check_finite(scene.intrinsics, f"{name}.intrinsics")
    if not float(np.asarray(scene.intrinsics)[0]) > 0:  # a negative focal length mirrors the image
        raise ValueError(f"{name}.intrinsics: expected a focal length > 0, got {float(np.asarray(scene.intrinsics)[0])}")
    light = scene.lighting
    _check_shape(light.ambient, (3,), f"{name}.lighting.ambient")
    _check_shape(light.directions, (None, 3), f"{name}.lighting.directions")
    _check_shape(light.colors, (len(light.directions), 3), f"{name}.lighting.colors")
    for what in ("ambient", "directions", "colors"):
        _check_finite(getattr(light, what), f"{name}.lighting.{what}")
    if len(light.directions) > MAX_LIGHTS:
        raise ValueError(f"{name}.lighting: expected at most {MAX_LIGHTS} lights, got {len(light.directions)}")
    for k, part in enumerate(scene.parts):
        where = f"{name}.parts[{k}]"
        _check_shape(part.vertices, (None, 3), f"{where}.vertices")
        n = len(part.vertices)
        for what, shape in (("normals", (n, 3)), ("colors", (n, 3)), ("faces", (None, 3)), ("rotation", (3, 3)),
                            ("translation", (3,))):
            _check_shape(getattr(part, what), shape, f"{where}.{what}")
        for what in ("vertices", "normals", "colors", "rotation", "translation"):
            _check_finite(getattr(part, what), f"{where}.{what}")
        if part.occlusion is not None:
            _check_shape(part.occlusion, (n,), f"{where}.occlusion")
            _check_finite(part.occlusion, f"{where}.occlusion")
        faces = np.asarray(part.faces)
        if faces.dtype.kind not in "iu":
            raise ValueError(f"{where}.faces: expected integers, got dtype {faces.dtype}")
        if faces.size and (int(faces.min()) < 0 or int(faces.max()) >= n):
            raise ValueError(f"{where}.faces: expected vertex indices in [0, {n}), got values in "
                             f"[{int(faces.min())}, {int(faces.max())}]")
        if not 1 <= int(part.label) <= 255:
            raise ValueError(f"{where}.label: expected 1..255, got {part.label}")

"""Headless OpenGL: pick ``PYOPENGL_PLATFORM`` (EGL, else OSMesa) before OpenGL is imported.

PyOpenGL reads ``PYOPENGL_PLATFORM`` once, when ``OpenGL`` is first imported, so the choice must be
made before anything imports ``OpenGL`` or ``pyrender``. :func:`select_gl_platform` probes the
system libraries with :mod:`ctypes` only (no OpenGL import): EGL counts as available when a display
can be initialised, as pyrender's EGL platform does it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from typing import Callable

__all__ = ["HeadlessGLError", "create_gl_context", "select_gl_platform"]

#: System packages that provide each platform, for error messages.
EGL_PACKAGES = "libegl1 + libegl-mesa0 (Debian/Ubuntu: `apt-get install libegl1 libegl-mesa0`; Fedora: mesa-libEGL)"
OSMESA_PACKAGES = "libosmesa6 (Debian/Ubuntu: `apt-get install libosmesa6`; Fedora: mesa-libOSMesa)"

_PLATFORMS = ("egl", "osmesa")


class HeadlessGLError(RuntimeError):
    """No headless OpenGL platform can be used; the message names what to install."""


def _load(names: tuple[str, ...]) -> ctypes.CDLL | None:
    for name in names:
        path = ctypes.util.find_library(name) if "." not in name else name
        if not path:
            continue
        try:
            return ctypes.CDLL(path)
        except OSError:
            continue
    return None


def egl_available() -> bool:
    """Whether an EGL display can be initialised (device platform if offered, else the default)."""
    lib = _load(("libEGL.so.1", "EGL"))
    if lib is None:
        return False
    try:
        lib.eglGetProcAddress.restype = ctypes.c_void_p
        lib.eglGetProcAddress.argtypes = [ctypes.c_char_p]
        lib.eglGetDisplay.restype = ctypes.c_void_p
        lib.eglGetDisplay.argtypes = [ctypes.c_void_p]
        lib.eglInitialize.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
        lib.eglTerminate.argtypes = [ctypes.c_void_p]
        display = None
        query = lib.eglGetProcAddress(b"eglQueryDevicesEXT")
        get_display = lib.eglGetProcAddress(b"eglGetPlatformDisplayEXT")
        if query and get_display:
            query_devices = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_int, ctypes.c_void_p, ctypes.POINTER(ctypes.c_int))(query)
            count = ctypes.c_int(0)
            if not query_devices(0, None, ctypes.byref(count)) or count.value < 1:
                return False
            devices = (ctypes.c_void_p * count.value)()
            query_devices(count.value, devices, ctypes.byref(count))
            platform_display = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p)(get_display)
            display = platform_display(0x313F, devices[0], None)  # EGL_PLATFORM_DEVICE_EXT
        else:
            display = lib.eglGetDisplay(None)
        if not display:
            return False
        major, minor = ctypes.c_int(), ctypes.c_int()
        if not lib.eglInitialize(display, ctypes.byref(major), ctypes.byref(minor)):
            return False
        lib.eglTerminate(display)
        return True
    except (AttributeError, OSError):
        return False


def osmesa_available() -> bool:
    """Whether the OSMesa library can be loaded."""
    return _load(("libOSMesa.so.8", "libOSMesa.so.6", "OSMesa")) is not None


def select_gl_platform(
    egl_probe: Callable[[], bool] = egl_available,
    osmesa_probe: Callable[[], bool] = osmesa_available,
) -> str:
    """Choose and set ``PYOPENGL_PLATFORM`` for headless rendering; return ``"egl"`` or ``"osmesa"``.

    A value already in the environment is kept (``egl`` or ``osmesa``). Otherwise EGL is chosen when a
    display can be initialised, else OSMesa when its library loads.

    Args:
        egl_probe: returns whether EGL works (replaceable in tests).
        osmesa_probe: returns whether OSMesa is installed.

    Raises:
        HeadlessGLError: if neither platform is present (the message names the system packages), if
            ``PYOPENGL_PLATFORM`` holds another value, or if OpenGL was imported before a headless
            platform was set.
    """
    current = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    if current:
        if current not in _PLATFORMS:
            raise HeadlessGLError(
                f"PYOPENGL_PLATFORM={current!r} cannot render offscreen; unset it or set it to 'egl' or 'osmesa'"
            )
        return current
    if "OpenGL" in sys.modules:
        raise HeadlessGLError(
            "OpenGL was imported before a headless platform was chosen; set PYOPENGL_PLATFORM=egl "
            "(or osmesa) in the environment, or import facenormals.data before pyrender/OpenGL"
        )
    if egl_probe():
        choice = "egl"
    elif osmesa_probe():
        choice = "osmesa"
    else:
        raise HeadlessGLError(
            "no headless OpenGL found: neither EGL nor OSMesa can be loaded. Install EGL with "
            f"{EGL_PACKAGES}, or OSMesa with {OSMESA_PACKAGES}. EGL is preferred: pyrender pins "
            "PyOpenGL 3.1.0, whose OSMesa binding is broken"
        )
    os.environ["PYOPENGL_PLATFORM"] = choice
    return choice


class _Context:
    """A current offscreen OpenGL context from pyrender's platform classes."""

    def __init__(self, platform: str) -> None:
        self.platform_name = platform
        if platform == "egl":
            from pyrender.platforms.egl import EGLPlatform

            self._platform = EGLPlatform(1, 1)
        else:
            from pyrender.platforms.osmesa import OSMesaPlatform

            self._platform = OSMesaPlatform(1, 1)
        self._platform.init_context()
        self._platform.make_current()
        # pyrender's Platform.__del__ calls delete_context, which for EGL also terminates the display
        # that all contexts of the process share: route it to delete(), which destroys this one only.
        self._platform.delete_context = self.delete

    def make_current(self) -> None:
        self._platform.make_current()

    def delete(self) -> None:
        """Destroy this context only: pyrender's ``delete_context`` would also terminate the EGL
        display, which every context of the process shares."""
        if self.platform_name == "egl":
            from OpenGL import EGL

            platform = self._platform
            if platform._egl_context is not None:
                EGL.eglMakeCurrent(platform._egl_display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
                EGL.eglDestroyContext(platform._egl_display, platform._egl_context)
                platform._egl_context = None
        elif getattr(self._platform, "_context", None) is not None:
            type(self._platform).delete_context(self._platform)


def create_gl_context() -> _Context:
    """Select the platform and create a current offscreen context through pyrender's platforms.

    Raises:
        HeadlessGLError: if no platform is available or the context cannot be created; the message
            says what to install.
    """
    platform = select_gl_platform()
    if platform == "egl" and not os.environ.get("DISPLAY"):
        # pyrender imports pyglet, whose default backend loads X libraries at import; a headless
        # GPU server often has none (seen on an H100 machine: libXrender missing)
        os.environ.setdefault("PYGLET_HEADLESS", "true")
    try:
        import pyrender  # noqa: F401
    except ImportError as error:
        missing = isinstance(error, ModuleNotFoundError) and error.name in ("pyrender", "OpenGL")
        if platform == "osmesa" and not missing and not osmesa_available():
            hint = (f"the OSMesa library is not installed; install EGL ({EGL_PACKAGES}) and unset PYOPENGL_PLATFORM "
                    "(EGL is the supported path: the OSMesa binding of PyOpenGL 3.1.0, pinned by pyrender, is broken)")
        elif platform == "osmesa" and not missing:
            hint = (f"PyOpenGL 3.1.0 (pinned by pyrender) has a broken OSMesa binding: install EGL ({EGL_PACKAGES}) "
                    "and unset PYOPENGL_PLATFORM")
        else:
            hint = ("pyrender and PyOpenGL are dependencies of facenormals: reinstall it (`pip install -e .` or "
                    "`pip install pyrender`)")

        raise HeadlessGLError(
            f"importing pyrender with PYOPENGL_PLATFORM={platform} failed ({error}); {hint}"
        ) from error
    except Exception as error:  # noqa: BLE001 - pyglet fails with AttributeError/OSError on missing X libraries
        raise HeadlessGLError(
            f"importing pyrender failed ({type(error).__name__}: {error}); without a display set "
            "PYGLET_HEADLESS=true, with one check its X libraries (libX11, libXrender)"
        ) from error
    try:
        return _Context(platform)
    except Exception as error:  # pyrender raises assertions, ImportError or ctypes errors here
        hint = (
            f"check the EGL driver ({EGL_PACKAGES})"
            if platform == "egl"
            else "PyOpenGL 3.1.0 (pinned by pyrender) has a broken OSMesa binding: install EGL "
            f"({EGL_PACKAGES}) or a PyOpenGL release with a working OSMesa binding"
        )
        raise HeadlessGLError(
            f"cannot create an offscreen OpenGL context with PYOPENGL_PLATFORM={platform} "
            f"({type(error).__name__}: {error}); {hint}"
        ) from error

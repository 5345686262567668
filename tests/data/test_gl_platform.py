import subprocess
import sys

import pytest

from facenormals.data import HeadlessGLError, select_gl_platform


def test_error_names_the_packages_to_install(monkeypatch):
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    monkeypatch.delitem(sys.modules, "OpenGL", raising=False)
    with pytest.raises(HeadlessGLError) as info:
        select_gl_platform(egl_probe=lambda: False, osmesa_probe=lambda: False)
    message = str(info.value)
    assert "libegl1" in message and "libosmesa6" in message and "apt-get install" in message
    assert "PYOPENGL_PLATFORM" not in __import__("os").environ


def test_egl_first_then_osmesa(monkeypatch):
    monkeypatch.delitem(sys.modules, "OpenGL", raising=False)
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    assert select_gl_platform(egl_probe=lambda: True, osmesa_probe=lambda: True) == "egl"
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    assert select_gl_platform(egl_probe=lambda: False, osmesa_probe=lambda: True) == "osmesa"
    import os

    assert os.environ["PYOPENGL_PLATFORM"] == "osmesa"


def test_an_explicit_choice_is_kept(monkeypatch):
    monkeypatch.setenv("PYOPENGL_PLATFORM", "osmesa")
    assert select_gl_platform(egl_probe=lambda: True, osmesa_probe=lambda: False) == "osmesa"
    monkeypatch.setenv("PYOPENGL_PLATFORM", "glx")
    with pytest.raises(HeadlessGLError, match="'glx' cannot render offscreen"):
        select_gl_platform()


def test_opengl_imported_too_early(monkeypatch):
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    monkeypatch.setitem(sys.modules, "OpenGL", object())
    with pytest.raises(HeadlessGLError, match="OpenGL was imported before"):
        select_gl_platform(egl_probe=lambda: True)


def test_importing_the_package_imports_no_opengl():
    code = "import sys, facenormals.data; assert 'OpenGL' not in sys.modules and 'pyrender' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_missing_pyrender_is_a_headless_gl_error(monkeypatch):
    from facenormals.data.gl_platform import create_gl_context

    monkeypatch.setenv("PYOPENGL_PLATFORM", "egl")
    monkeypatch.setitem(sys.modules, "pyrender", None)  # makes `import pyrender` fail
    with pytest.raises(HeadlessGLError, match=r"PYOPENGL_PLATFORM=egl failed .*pip install pyrender"):
        create_gl_context()


def test_pyrender_import_is_headless_without_a_display():
    # a fresh interpreter without DISPLAY: pyglet (imported by pyrender) must take its headless
    # backend, and a failing import is a HeadlessGLError, not pyglet's AttributeError from deep inside
    code = (
        "import builtins, os, sys\n"
        "os.environ.pop('DISPLAY', None); os.environ.pop('PYGLET_HEADLESS', None)\n"
        "os.environ['PYOPENGL_PLATFORM'] = 'egl'\n"
        "real = builtins.__import__\n"
        "def fake(name, *args, **kwargs):\n"
        "    if name == 'pyrender':\n"
        "        raise AttributeError(\"'NoneType' object has no attribute 'XRenderFindVisualFormat'\")\n"
        "    return real(name, *args, **kwargs)\n"
        "builtins.__import__ = fake\n"
        "from facenormals.data.gl_platform import HeadlessGLError, create_gl_context\n"
        "try:\n"
        "    create_gl_context()\n"
        "except HeadlessGLError as error:\n"
        "    assert 'PYGLET_HEADLESS' in str(error) and 'AttributeError' in str(error), error\n"
        "else:\n"
        "    raise SystemExit('no error')\n"
        "assert os.environ['PYGLET_HEADLESS'] == 'true'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_missing_pyrender_under_osmesa_says_to_install_it(monkeypatch):
    from facenormals.data.gl_platform import create_gl_context

    monkeypatch.setenv("PYOPENGL_PLATFORM", "osmesa")
    monkeypatch.setitem(sys.modules, "pyrender", None)
    with pytest.raises(HeadlessGLError, match=r"PYOPENGL_PLATFORM=osmesa failed .*pip install pyrender"):
        create_gl_context()


@pytest.mark.parametrize("installed, message", [(False, "the OSMesa library is not installed; install EGL"),
                                                (True, "has a broken OSMesa binding: install EGL")])
def test_an_osmesa_failure_is_explained_by_its_cause(installed, message):
    code = (
        "import builtins, os\n"
        "os.environ['PYOPENGL_PLATFORM'] = 'osmesa'\n"
        "real = builtins.__import__\n"
        "def fake(name, *args, **kwargs):\n"
        "    if name == 'pyrender':\n"
        "        raise ImportError(\"('Unable to load OpenGL library', 'OSMesa: cannot open shared object file')\")\n"
        "    return real(name, *args, **kwargs)\n"
        "builtins.__import__ = fake\n"
        "from facenormals.data import gl_platform\n"
        f"gl_platform.osmesa_available = lambda: {installed}\n"
        "try:\n"
        "    gl_platform.create_gl_context()\n"
        "except gl_platform.HeadlessGLError as error:\n"
        "    print(error)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "PYOPENGL_PLATFORM=osmesa failed" in out and message in out, out

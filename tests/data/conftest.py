"""Fixtures for the synthetic-data tests: generators that skip where no headless OpenGL exists."""

from __future__ import annotations

import contextlib

import pytest

from facenormals.data import HeadlessGLError, SynthConfig, SyntheticHeadGenerator

from tests.conftest import ict_archive_or_skip


def make_generator(spec: str, config: SynthConfig | None = None, grid: int = 2) -> SyntheticHeadGenerator:
    """A generator whose renderer is created now; skips the test without headless OpenGL or ICT."""
    if spec == "ict":
        spec = str(ict_archive_or_skip())
    generator = SyntheticHeadGenerator(spec, config, grid=grid)
    try:
        generator.renderer
    except HeadlessGLError as error:
        pytest.skip(f"no headless OpenGL: {error}")
    return generator


@pytest.fixture(scope="session", params=["ict", "builtin"])
def generator(request):
    """The default generator (4 tiles) on ICT-FaceKit and on the built-in head."""
    gen = make_generator(request.param)
    yield gen
    gen.close()


@pytest.fixture(scope="session")
def samples(generator):
    """Eight samples of dataset seed 11 (with hair, caps, occluders, any pose)."""
    return generator.generate(11, range(8))


@contextlib.contextmanager
def configured(generator: SyntheticHeadGenerator, config: SynthConfig):
    """Temporarily render with another configuration of the same image size (reuses the context)."""
    assert config.image_size == generator.config.image_size and config.supersample == generator.config.supersample
    previous = generator.config
    generator.config = config
    try:
        yield generator
    finally:
        generator.config = previous

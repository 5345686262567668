"""The API pages' docstrings go through docs/scripts/griffe_sphinx_roles.py (mkdocs.yml)."""

import importlib.util
from pathlib import Path

import pytest

# the docs extra (mkdocs brings PyYAML, mkdocstrings brings griffe); the test extra alone skips these
yaml = pytest.importorskip("yaml")
pytest.importorskip("griffe")

ROOT = Path(__file__).resolve().parents[1]


def load_extension():
    spec = importlib.util.spec_from_file_location("griffe_sphinx_roles", ROOT / "docs" / "scripts" / "griffe_sphinx_roles.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_sphinx_roles_become_markdown():
    convert = load_extension().sphinx_roles_to_markdown
    assert convert(":math:`a = \\frac{1}{z} K R (p + t)`") == "$a = \\frac{1}{z} K R (p + t)$"
    assert convert("see :func:`~facenormals.geometry.project_points` and :class:`torch.Tensor`") == \
        "see `project_points` and `torch.Tensor`"
    assert convert(":meth:`the fit <facenormals.fitting.fit_head>`") == "`the fit`"
    block = "Minimises\n\n.. math::\n\n    F(x) = \\tfrac12 \\lVert r \\rVert^2,\n\nwhere r ...\n"
    assert convert(block) == "Minimises\n\n$$\nF(x) = \\tfrac12 \\lVert r \\rVert^2,\n$$\n\nwhere r ...\n"
    indented = "Args:\n    x: the point.\n\n        .. math::\n\n            y = 2 x\n"
    assert convert(indented) == "Args:\n    x: the point.\n\n        $$\n        y = 2 x\n        $$\n\n"


def test_mkdocs_loads_the_extension_and_mathjax():
    class Loader(yaml.SafeLoader):  # mkdocs.yml may hold !!python tags; none are needed here
        pass

    config = yaml.load((ROOT / "mkdocs.yml").read_text(), Loader=Loader)
    handler = next(p for p in config["plugins"] if isinstance(p, dict) and "mkdocstrings" in p)
    options = handler["mkdocstrings"]["handlers"]["python"]["options"]
    assert "docs/scripts/griffe_sphinx_roles.py:SphinxRoles" in options["extensions"]
    assert "javascripts/mathjax.js" in config["extra_javascript"]
    assert (ROOT / "docs" / "javascripts" / "mathjax.js").is_file()

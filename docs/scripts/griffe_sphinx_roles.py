"""A Griffe extension for the API pages: the docstrings' Sphinx roles as Markdown.

The docstrings are Google-style but mark maths and cross-references the Sphinx way
(``:math:`a_i```, ``.. math::`` blocks, ``:func:`~facenormals.x.y```), which mkdocstrings shows
verbatim. This turns them into arithmatex maths (``$…$``, ``$$…$$``) and code names, so that the
API pages read like the prose pages. Loaded by ``mkdocs.yml`` (``extensions:`` of the Python handler).
"""

from __future__ import annotations

import re

import griffe

_MATH = re.compile(r":math:`([^`]+)`")
_REFERENCE = re.compile(r":(?:func|class|meth|attr|data|mod|obj|exc):`(~?)([^`]+)`")
_BLOCK = re.compile(r"^(?P<indent>[ \t]*)\.\. math::[ \t]*\n(?P<body>(?:[ \t]*\n|(?P=indent)[ \t]+\S[^\n]*\n?)+)",
                    re.MULTILINE)


def _reference(match: re.Match) -> str:
    short, target = match.groups()
    titled = re.fullmatch(r"(.+?)\s*<(.+)>", target)  # :func:`title <target>`
    if titled:
        return f"`{titled.group(1)}`"
    return f"`{target.rsplit('.', 1)[-1] if short else target}`"


def _block(match: re.Match) -> str:
    indent = match.group("indent")
    lines = [line.strip() for line in match.group("body").splitlines() if line.strip()]
    return "\n".join([f"{indent}$$", *(indent + line for line in lines), f"{indent}$$", ""]) + "\n"


def sphinx_roles_to_markdown(text: str) -> str:
    """``text`` with ``.. math::`` blocks, ``:math:`` and cross-reference roles as Markdown.

    Example:
        >>> sphinx_roles_to_markdown("Uses :math:`a_i` and :func:`~facenormals.geometry.project_points`.")
        'Uses $a_i$ and `project_points`.'
    """
    text = _BLOCK.sub(_block, text)
    text = _MATH.sub(lambda m: f"${m.group(1)}$", text)
    return _REFERENCE.sub(_reference, text)


class SphinxRoles(griffe.Extension):
    """Rewrite every loaded object's docstring with :func:`sphinx_roles_to_markdown`."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: object) -> None:
        if obj.docstring is not None:
            obj.docstring.value = sphinx_roles_to_markdown(obj.docstring.value)

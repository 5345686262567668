"""A package's names imported on first use (PEP 562), so that importing the package stays cheap."""

from __future__ import annotations

import importlib
import importlib.util
from typing import Any, Callable


def lazy_names(package: str, sources: dict[str, str], namespace: dict[str, Any],
               subpackages: bool = False) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level ``__getattr__`` and ``__dir__`` of ``package``: each name of ``sources`` is
    imported from the module ``package.sources[name]`` on first use and kept in ``namespace`` (the
    package's ``globals()``); with ``subpackages``, any other public name that is a submodule of
    ``package`` is imported too (``facenormals.fitting``)."""

    def __getattr__(name: str) -> Any:
        if name in sources:
            value = getattr(importlib.import_module(f"{package}.{sources[name]}"), name)
        elif (subpackages and name.isidentifier() and not name.startswith("_")
              and importlib.util.find_spec(f"{package}.{name}")):
            value = importlib.import_module(f"{package}.{name}")
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*namespace, *sources})

    return __getattr__, __dir__

"""Registries: a name -> thing mapping whose look-up names the valid choices when it fails.

One mechanism for every "pick by name" in radiomap (fusion backends, response fitters, vignetting models,
response families, file formats, subcommands), as colour-science's ``validate_method`` and its
``*_METHODS`` mappings do::

    BACKENDS = Registry("backend", {"tsdf": "mapping.fusion.tsdf:TSDFBackend", ...})
    BACKENDS["voxel"]   # ValueError: backend must be one of tsdf, surfel, got 'voxel'

An entry may be the thing itself or ``"module:attribute"``, imported on first use (so that choosing the
surfel backend does not import Open3D, and listing the names imports nothing).
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping
from typing import Any


class Registry(Mapping):
    """An ordered, read-only mapping of names to things (or to ``"module:attribute"`` paths imported lazily).

    kind: what the names choose, for the error message ("backend", "response method", ...).
    """

    def __init__(self, kind: str, entries: Mapping[str, Any]) -> None:
        self.kind = kind
        self._entries = dict(entries)

    def __getitem__(self, name: str) -> Any:
        entry = self._entries[validate_name(name, self._entries, self.kind)]
        if isinstance(entry, str) and ":" in entry:
            module, _, attribute = entry.partition(":")
            return getattr(importlib.import_module(module), attribute)
        return entry

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def names(self) -> tuple[str, ...]:
        return tuple(self._entries)

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, {', '.join(self._entries)})"


def validate_name(name: Any, valid: Mapping[str, Any] | tuple[str, ...] | list[str], kind: str) -> str:
    """``name`` if it is one of ``valid``, else a ValueError that lists the valid names."""
    if isinstance(name, str) and name in valid:
        return name
    raise ValueError(f"{kind} must be one of {', '.join(valid)}, got {name!r}")


__all__ = ["Registry", "validate_name"]

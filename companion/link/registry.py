"""A registry of classes by name, filled by subclassing: defining a class registers it.

Both autopilot registries use it: the agent's dialects (`companion.link.dialects.DIALECTS`)
and the SITL's autopilot behaviours (`sim_bridge.sitl.autopilots.AUTOPILOTS`). Every
concrete (non-abstract) subclass of the base class, wherever it is defined, is an entry
under its `name`, with one instance made on first sight. The registry's own package is
imported whole when the registry is made, so the autopilots shipped with it are always
there; a class defined anywhere else (a plug-in, a test's toy autopilot) is there as soon
as its module has been imported. Lookups re-scan the subclasses when a name is missing,
so nothing has to call a `register()`.
"""
from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Iterator, Mapping
from typing import Generic, TypeVar

T = TypeVar("T")


class RegistryConflict(TypeError):
    """Two classes claim one name (or one value of a unique attribute)."""


class SubclassRegistry(Mapping[str, T], Generic[T]):
    """name -> the one instance of every concrete subclass of `base` defined so far.

    Args:
        base: the (abstract) base class; its concrete subclasses have a class attribute `name`.
        package: a package whose modules are all imported now (except `base` and `_private`
            ones), so that the classes it ships are registered.
        unique: other class attributes whose values must differ between entries
            (e.g. HEARTBEAT.autopilot of dialects).

    Raises (on any lookup):
        RegistryConflict: two classes with one name or one value of a `unique` attribute.
    """

    def __init__(self, base: type, package: str | None = None, unique: tuple[str, ...] = ()):
        self._base = base
        self._unique = unique
        self._entries: dict[str, T] = {}
        if package is not None:
            pkg = importlib.import_module(package)
            for info in pkgutil.iter_modules(pkg.__path__):
                if info.name != "base" and not info.name.startswith("_"):
                    importlib.import_module(f"{package}.{info.name}")
        self.refresh()

    def refresh(self) -> None:
        """Register the concrete subclasses defined since the last look."""
        stack: list[type] = list(self._base.__subclasses__())
        while stack:
            cls = stack.pop()
            stack += cls.__subclasses__()
            if inspect.isabstract(cls):
                continue
            name = getattr(cls, "name")
            have = self._entries.get(name)
            if have is None:
                self._check_unique(cls)
                self._entries[name] = cls()
            elif type(have) is not cls:
                raise RegistryConflict(f"two {self._base.__name__} classes named {name!r}: "
                                       f"{type(have).__module__}.{type(have).__qualname__} and "
                                       f"{cls.__module__}.{cls.__qualname__}")

    def _check_unique(self, cls: type) -> None:
        for attr in self._unique:
            value = getattr(cls, attr)
            for other in self._entries.values():
                if getattr(other, attr) == value:
                    raise RegistryConflict(f"{self._base.__name__} {getattr(cls, 'name')!r} has {attr}={value!r}, "
                                           f"as {getattr(other, 'name')!r} has")

    def __getitem__(self, name: str) -> T:
        if name not in self._entries:
            self.refresh()
        return self._entries[name]

    def __iter__(self) -> Iterator[str]:
        self.refresh()
        return iter(list(self._entries))

    def __len__(self) -> int:
        self.refresh()
        return len(self._entries)

    def __contains__(self, name: object) -> bool:
        if name not in self._entries:
            self.refresh()
        return name in self._entries

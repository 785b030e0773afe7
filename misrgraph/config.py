"""Typed dataclass configurations that reject unknown keys.

Every user-facing configuration of misrgraph is a frozen dataclass deriving from
:class:`Config`. ``Config.from_dict`` refuses keys the dataclass does not declare (a typo in a
scripted campaign must fail loudly, not be ignored) and checks the basic type of each value.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, Mapping, TypeVar

from misrgraph.errors import InputError

__all__ = ["Config"]

C = TypeVar("C", bound="Config")


@dataclasses.dataclass(frozen=True)
class Config:
    """Base class of all configuration dataclasses."""

    @classmethod
    def from_dict(cls: type[C], data: Mapping[str, Any] | None = None, **overrides: Any) -> C:
        """Build a config from a mapping, rejecting unknown keys with an :class:`InputError`."""
        merged = dict(data or {})
        merged.update(overrides)
        fields = {f.name: f for f in dataclasses.fields(cls)}
        for key in merged:
            if key not in fields:
                raise InputError(f"{cls.__name__}.{key}", merged[key], sorted(fields))
        hints = typing.get_type_hints(cls)
        kwargs: dict[str, Any] = {}
        for key, value in merged.items():
            kwargs[key] = _coerce(f"{cls.__name__}.{key}", value, hints.get(key))
        return cls(**kwargs)

    def to_dict(self) -> dict[str, Any]:
        """Plain-dict view (JSON-friendly for scalars and tuples)."""
        return dataclasses.asdict(self)

    def replace(self: C, **changes: Any) -> C:
        """Copy with some fields changed; unknown fields are rejected."""
        return type(self).from_dict(self.to_dict(), **changes)


def _coerce(name: str, value: Any, hint: Any) -> Any:
    if hint in (float,):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(name, value, "a number")
        return float(value)
    if hint in (int,):
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(name, value, "an integer")
        return int(value)
    if hint in (bool,):
        if not isinstance(value, bool):
            raise InputError(name, value, "true or false")
        return value
    if hint in (str,):
        if not isinstance(value, str):
            raise InputError(name, value, "a string")
        return value
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if value is not None and len(args) == 1 and len(typing.get_args(hint)) == 2:
        hint = args[0]  # Optional[X]: a value is an X
    if isinstance(hint, type) and issubclass(hint, Config):
        if isinstance(value, hint):
            return value
        if not isinstance(value, Mapping):
            raise InputError(name, value, f"a mapping of {hint.__name__} fields")
        return hint.from_dict(value)
    origin = typing.get_origin(hint)
    if (hint is tuple or origin is tuple) and isinstance(value, (list, tuple)):
        return tuple(value)
    return value

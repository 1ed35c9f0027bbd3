"""String options that resolve through an Enum and list the valid values when a name is wrong."""

from __future__ import annotations

import enum

__all__ = ["Option", "option_label"]


class Option(str, enum.Enum):
    """A string-valued option; :func:`option_label` names it in error messages."""

    @classmethod
    def parse(cls, value):
        """The member for ``value`` (a member or its string); a clear ValueError otherwise."""
        try:
            return cls(value)
        except ValueError:
            raise ValueError(f"unknown {_LABELS.get(cls, cls.__name__)} {value!r}; choose one of: "
                             f"{', '.join(m.value for m in cls)}") from None


_LABELS: dict[type, str] = {}


def option_label(label: str):
    """Class decorator naming an :class:`Option` in error messages (``unknown <label> 'x'; choose one of ...``)."""

    def register(cls):
        _LABELS[cls] = label
        return cls

    return register

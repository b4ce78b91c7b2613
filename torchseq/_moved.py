"""Names that moved: a package's ``__getattr__`` that still finds them, with a warning.

A public name that leaves a module keeps working where users met it for a while: the
package's module ``__getattr__`` (PEP 562) returns the object from its new home and raises a
:class:`DeprecationWarning` naming that home. Nothing is imported until a moved name is used.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable


def moved_names(module: str, moves: dict[str, str]) -> Callable[[str], object]:
    """A module ``__getattr__`` for ``moves``: ``{old name: "new.module.name"}``.

    Args:
        module: the module that used to hold the names (for the messages).
        moves: each old name and the dotted path of its new home.

    Returns:
        ``__getattr__(name)``: the moved object (with a ``DeprecationWarning``), or
        ``AttributeError`` for any other name.
    """

    def __getattr__(name: str) -> object:
        target = moves.get(name)
        if target is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        home, _, attr = target.rpartition(".")
        warnings.warn(f"{module}.{name} moved to {target}; import it from {home}",
                      DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module(home), attr)

    return __getattr__

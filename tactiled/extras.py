"""Optional integrations: import their heavy dependencies only when used, with a one-line error naming the extra."""

from __future__ import annotations

import importlib
from types import ModuleType

from tactiled.errors import TactiledError


def need(module: str, extra: str) -> ModuleType:
    """Import ``module``, or raise :class:`TactiledError` telling to install ``tactiled[extra]``."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise TactiledError(f"{module}: not importable ({exc}); install it with: pip install 'tactiled[{extra}]'") from None

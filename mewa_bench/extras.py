"""Optional dependencies: import a module an extra provides, or fail with the `pip install` that adds it.

The core install (game, design, envs, protocol, evaluate, leaderboard, suites) needs none of them;
each command that does imports its modules through `require`, only when it runs. Imports nothing
of the package, so every layer may use it.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType


class MissingExtra(ImportError):
    """A module of an optional extra cannot be imported; the message names the extra and how to install it."""

    def __init__(self, module: str, extra: str, feature: str, reason: str | None = None) -> None:
        self.module, self.extra, self.feature = module, extra, feature
        self.reason = reason or f"{module.partition('.')[0]} is not installed"
        super().__init__(f"{feature} needs the {extra} extra ({self.reason}): pip install 'mewa-bench[{extra}]'",
                         name=module)


def require(module: str, extra: str, feature: str) -> ModuleType:
    """`import module` (a dotted name too), or raise MissingExtra saying which extra `feature` needs."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise MissingExtra(module, extra, feature, _reason(module, e)) from e


def _reason(module: str, error: ImportError) -> str | None:
    """None when the package is not installed; else the error of an installed package that fails to import."""
    if importlib.util.find_spec(module.partition(".")[0]) is None:
        return None
    return f"importing {module} failed: {error}"

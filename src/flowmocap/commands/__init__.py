"""Sub-commands of ``flowmocap`` that live in their own modules.

Every module in this package that defines ``register(subparsers)`` is picked up by
:func:`flowmocap.cli.build_parser`; ``register`` adds one sub-parser and sets its
``func`` default to a function ``(args) -> int`` (exit code). Commands import their
heavy dependencies inside that function, so ``flowmocap --help`` stays fast.
"""

from __future__ import annotations

import importlib
import pkgutil


def register_all(subparsers) -> None:
    """Add the sub-parser of every command module in this package, in name order."""
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(subparsers)

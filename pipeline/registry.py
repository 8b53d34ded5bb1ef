"""Stage lookup by name.  The stage list itself is the composition root's
(``dermis.STAGES``, ``dermis.COMMANDS``); the engine imports stage modules only through
:func:`stage` and :func:`command`."""
from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["STAGE_NAMES", "stage", "COMMANDS", "command"]


def _stages() -> dict[str, str]:
    import dermis
    return dict(dermis.STAGES)


STAGE_NAMES: tuple[str, ...] = tuple(_stages())


def _commands() -> dict[str, str]:
    import dermis
    return dict(dermis.COMMANDS)


COMMANDS: tuple[str, ...] = tuple(_commands())


def command(name: str) -> ModuleType:
    """The module of CLI subcommand ``name``: exports add_parser(subparsers) and run(args)."""
    return importlib.import_module(_commands()[name])


def stage(name: str) -> ModuleType:
    """The module of stage ``name``: exports NAME, VERSION, KERNELS, node(...) and run(...)."""
    return importlib.import_module(_stages()[name])

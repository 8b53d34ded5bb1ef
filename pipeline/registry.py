"""Stage and model lookup by name.  The lists themselves are the composition root's
(``dermis.STAGES``, ``dermis.MODELS``, ``dermis.COMMANDS``); the engine imports stage and
model modules only through :func:`stage`, :func:`model` and :func:`command`."""
from __future__ import annotations

import importlib
from types import ModuleType

from .errors import ConfigError

__all__ = ["STAGE_NAMES", "stage", "MODEL_NAMES", "model_names", "default_models", "term_bases",
           "model", "model_module", "section", "COMMANDS", "command"]


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


def _models() -> dict[str, str]:
    import dermis
    return dict(dermis.MODELS)


MODEL_NAMES: tuple[str, ...] = tuple(_models())


def model_names() -> tuple[str, ...]:
    """The registered model names, read now (a plugin may register one after import)."""
    return tuple(_models())


def default_models() -> tuple[str, ...]:
    """The models a scene renders unless it says otherwise (``dermis.THESIS_MODELS``)."""
    import dermis
    return tuple(dermis.THESIS_MODELS)


def term_bases() -> tuple[str, ...]:
    """Names of the models a term model (e.g. the asperity layer) may sit on."""
    out = []
    for name in model_names():
        out += [b.name for b in model(name).bases if b.name not in out]
    return tuple(out)


def section(name: str) -> ModuleType:
    """The module that parses and validates scene section ``name`` (``dermis.SECTIONS``)."""
    import dermis
    return importlib.import_module(dict(dermis.SECTIONS)[name])


def model_module(name: str) -> str:
    """The module that declares model ``name`` (a node that renders it hashes its code)."""
    modules = _models()
    if name not in modules:
        raise ConfigError(f"model = {name!r}: must be one of {', '.join(modules)}")
    return modules[name]


def model(name: str):
    """The :class:`~dermis.models.model.Model` named ``name`` (its module's ``MODEL``)."""
    return importlib.import_module(model_module(name)).MODEL

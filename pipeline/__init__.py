"""dermis engine: scene config, stage graph, artifact cache, OpenCL runtime, CLI."""
from .errors import DermisError, ConfigError

__all__ = ["DermisError", "ConfigError"]

"""Error types: anything the user can fix is a :class:`DermisError` (exit code 2)."""


class DermisError(Exception):
    """A problem the user can fix (bad scene, missing file, no OpenCL runtime)."""

    exit_code = 2


class ConfigError(DermisError):
    """A scene or layer file failed validation; the message names file, key, value and rule."""


class CacheLockedError(DermisError):
    """Another dermis process holds the cache directory."""

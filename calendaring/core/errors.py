"""Exception types shared by the host and device layers.

See also: :mod:`calendaring.core.cli_contract` (the exit code of each error type).
"""

from __future__ import annotations


class ConfigError(ValueError):
    """Invalid configuration: names the key, the value and what is allowed.

    Args:
        key: dotted configuration key, e.g. ``materials.AM.youngs_modulus``.
        value: the offending value.
        allowed: human-readable description of the allowed range or type.
    """

    def __init__(self, key: str, value: object, allowed: str) -> None:
        self.key = key
        self.value = value
        self.allowed = allowed
        super().__init__(f"{key} = {value!r} is invalid: allowed {allowed}")

    def with_prefix(self, prefix: str) -> ConfigError:
        """Return the same error with ``prefix.`` prepended to the key."""
        key = f"{prefix}.{self.key}" if prefix else self.key
        return ConfigError(key, self.value, self.allowed)


class SimulationError(RuntimeError):
    """A simulation stopped because it went unstable or ran out of capacity.

    The message names the quantity, the step and the particle(s) involved.
    """

    def __init__(self, message: str, *, step: int | None = None, particle_ids=None) -> None:
        self.step = step
        self.particle_ids = list(particle_ids) if particle_ids is not None else []
        super().__init__(message)

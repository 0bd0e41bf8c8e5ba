"""Layer 0, the foundation every other layer stands on: errors, SI unit helpers, atomic file
writes, the run configuration (frozen dataclasses loaded strictly from TOML) and the command-line
error contract shared by the four CLIs.

Imports nothing else of the project and never Taichi.

See also: :mod:`calendaring.engine` (layer 1), ``docs/architecture.md``.
"""

"""DEM simulation of Li-ion electrode calendering with particle breakage.

Importing this package has no Taichi side effects: the runtime is started only by
:func:`calendaring.backend.init_taichi`.
"""

from calendaring._version import __version__

__all__ = ["__version__"]

"""The thesis application: the thesis' data and scenarios, the needle-insertion studies (2D
phantom and 3D phantom), the simulated rig, and the studies behind the ``jaxrkpm`` command.

Its names are declared in ``__init__.pyi`` and load on first use (the command line reads the
thesis' data without loading JAX).
"""
import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)

"""dosppm_core: the rendering library of dosppm (scene, kernels, SPPM
statistics, film). It knows nothing of sockets; `services/` drives it."""
from . import _kernel_cache

__version__ = "0.1.0"
_kernel_cache.refresh()

"""dosppm_core: the rendering library of dosppm (scene, kernels, SPPM
statistics, film). It knows nothing of sockets; `services/` drives it."""
import os

# numba's parallel kernels run on GNU OpenMP here, whose threads spin at
# every barrier by default. When another process holds a core (a second
# tracer, the server, a test runner) a spinning thread can wait a whole
# scheduler slice per barrier: measured 90-130 ms instead of 0.2 ms for one
# 1000-photon bounce. Passive waiting costs nothing measurable when alone.
# Set before numba loads libgomp; a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "passive")
# The render server calls parallel kernels from two threads at once (the
# message loop emits photons while the statistics thread gathers). numba's
# fallback 'workqueue' layer aborts on that ("Concurrent access has been
# detected"), as on a minimal host without libgomp: ask for a thread-safe
# layer (OpenMP or TBB), so a missing one is a clear error at the start.
os.environ.setdefault("NUMBA_THREADING_LAYER", "threadsafe")

from dosppm_core import _kernel_cache  # noqa: E402

__version__ = "0.1.0"
_kernel_cache.refresh()

# The Python API (dosppm_core.api): dp.load, dp.render, dp.render_stops,
# dp.write, dp.Image. Loaded on first use, so that importing the package
# stays cheap for the services (no numba, no Embree until needed).
_API = ("Image", "load", "render", "render_stops", "write")


def __getattr__(name: str):
    if name in _API:
        from dosppm_core import api
        return getattr(api, name)
    raise AttributeError(f"module 'dosppm_core' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_API))

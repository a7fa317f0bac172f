"""dosppm_core: the rendering library of dosppm (scene, kernels, SPPM
statistics, film). It knows nothing of sockets; `services/` drives it."""
__version__ = "0.1.0"

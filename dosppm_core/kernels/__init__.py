"""numba kernels. Each takes and returns whole batches as arrays; all are
compiled with cache=True so the compile cost is paid once per machine."""

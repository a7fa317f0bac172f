"""Counter-based random numbers: every path carries a 64-bit state derived
from (seed, job, path index), so a path draws the same numbers whatever
batch, chunk or process traces it. This is what makes a re-emitted job
trace the same photons and keeps chunked and unchunked renders equal.

The generator is SplitMix64 (Steele et al. 2014): a Weyl sequence through a
bijective mixer; good enough for Monte Carlo and trivially seekable.
"""
import numba as nb
import numpy as np

GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31 = np.uint64(30), np.uint64(27), np.uint64(31)
_S40 = np.uint64(40)
_INV24 = np.float32(1.0 / (1 << 24))

# Job ids are namespaced so eye and photon streams never collide.
EYE_STREAM = np.uint64(1) << np.uint64(62)


@nb.njit(cache=True)
def mix64(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@nb.njit(cache=True)
def path_state(seed, job, index):
    """Initial state of path `index` of job `job` (all uint64)."""
    return mix64(mix64(np.uint64(seed) ^ mix64(np.uint64(job) + GOLDEN)) + np.uint64(index))


@nb.njit(cache=True)
def next_float(state):
    """Return (new_state, u) with u uniform in [0, 1) as float32."""
    state = np.uint64(state) + GOLDEN
    u = np.float32(mix64(state) >> _S40) * _INV24
    return state, u


@nb.njit(cache=True, parallel=True)
def path_states(seed, job, first_index, count):
    out = np.empty(count, np.uint64)
    for i in nb.prange(count):
        out[i] = path_state(np.uint64(seed), np.uint64(job), np.uint64(first_index + i))
    return out

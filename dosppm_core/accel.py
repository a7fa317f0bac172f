"""The ray-tracing aggregate: the only module that touches Embree.

Embree 4 is the library bundled in the embreex wheel, driven directly:
- the BVH is built through ctypes over our own arrays (Embree's shared
  buffers: no copy). A ctypes call releases the GIL, so a chunk loads on a
  prefetch thread while another thread traces. embreex's own mesh class
  copies the mesh element by element and builds the BVH holding the GIL
  (0.85 s + 0.3 s for 1.25M triangles), which serialised every chunk load
  with tracing in OSPPM;
- rays are traced by a numba kernel that calls `rtcIntersect1` in a
  parallel loop without the GIL (numba resolves the symbol by name, so the
  kernel caches like every other).
The scene is built with Embree's robust flag, as embreex builds it: the
closest hit of every ray equals embreex's (tests/test_accel.py).
"""
from __future__ import annotations

import ctypes
import glob
import os
import threading

import embreex
import llvmlite.binding
import numba
import numpy as np
from numba import njit, prange, types

MISS = -1
_MISS_T = np.float32(1e37)    # t reported for a miss without tmax (as embreex)
_MIN_SPLIT = 4096             # below this a second thread costs more than it saves
_BLOCK = 512                  # rays per parallel work item

# Embree 4 API constants (rtcore_common.h, rtcore_geometry.h, rtcore_scene.h).
_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX, _BUFFER_TYPE_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003
_SCENE_FLAG_ROBUST = 1 << 2
_DEVICE_PROPERTY_VERSION_MAJOR = 1
# RTCRayHit as 32-bit words: the ray (org, tnear, dir, time, tfar, mask, id,
# flags) then the hit (Ng, u, v, primID, geomID, instID...). 32 words covers
# any instance-level count this build may have.
_RAYHIT_WORDS = 32
_TFAR, _MASK, _FLAGS, _U, _V, _PRIM, _GEOM, _INST = 8, 9, 11, 15, 16, 17, 18, 19


# -- the library -----------------------------------------------------------------
def _library_path() -> str:
    here = os.path.dirname(os.path.abspath(embreex.__file__))
    # Linux wheels keep it in embreex.libs/, macOS ones in embreex/.dylibs/.
    patterns = [os.path.join(here, "..", "embreex.libs", "libembree4*"),
                os.path.join(here, ".dylibs", "libembree4*"),
                os.path.join(here, "libembree4*")]
    for pattern in patterns:
        found = sorted(glob.glob(pattern))
        if found:
            return found[0]
    raise ImportError(f"no libembree4 found beside embreex in {here}")


def _load_library() -> ctypes.CDLL:
    path = _library_path()
    lib = ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)
    llvmlite.binding.load_library_permanently(path)   # numba links rtcIntersect1 by name
    vp, u, sz = ctypes.c_void_p, ctypes.c_uint, ctypes.c_size_t
    for name, res, args in (
            ("rtcNewDevice", vp, [ctypes.c_char_p]),
            ("rtcGetDeviceProperty", ctypes.c_ssize_t, [vp, ctypes.c_int]),
            ("rtcGetDeviceError", ctypes.c_int, [vp]),
            ("rtcNewScene", vp, [vp]),
            ("rtcSetSceneFlags", None, [vp, ctypes.c_int]),
            ("rtcNewGeometry", vp, [vp, ctypes.c_int]),
            ("rtcSetSharedGeometryBuffer", None, [vp, ctypes.c_int, u, ctypes.c_int, vp, sz, sz, sz]),
            ("rtcCommitGeometry", None, [vp]),
            ("rtcAttachGeometry", u, [vp, vp]),
            ("rtcReleaseGeometry", None, [vp]),
            ("rtcCommitScene", None, [vp]),
            ("rtcReleaseScene", None, [vp])):
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args
    return lib


_LIB = _load_library()
_DEVICE = None
_DEVICE_LOCK = threading.Lock()


def _device():
    """One Embree device per process, made on first use."""
    global _DEVICE
    with _DEVICE_LOCK:
        if _DEVICE is None:
            device = _LIB.rtcNewDevice(None)
            if not device:
                raise RuntimeError("Embree: rtcNewDevice failed")
            major = _LIB.rtcGetDeviceProperty(device, _DEVICE_PROPERTY_VERSION_MAJOR)
            if major != 4:
                raise ImportError(f"{_library_path()}: Embree {major}, dosppm needs Embree 4")
            _DEVICE = device
        return _DEVICE


# -- the trace kernel --------------------------------------------------------------
_intersect1 = types.ExternalFunction("rtcIntersect1", types.void(types.uintp, types.uintp, types.uintp))


@njit(nogil=True, cache=True)
def _trace_range(scene, origin, direction, tmax, has_tmax, start, stop, prim, t, u, v):
    """Rays [start, stop) one at a time through a 16-byte aligned RTCRayHit."""
    store = np.empty(_RAYHIT_WORDS + 4, np.float32)
    skip = ((16 - store.ctypes.data % 16) % 16) // 4
    f = store[skip:skip + _RAYHIT_WORDS]
    w = f.view(np.int32)
    address = store.ctypes.data + 4 * skip
    for i in range(start, stop):
        for k in range(3):
            f[k] = origin[i, k]
            f[4 + k] = direction[i, k]
        f[3] = 0.0                      # tnear
        f[7] = 0.0                      # time
        f[_TFAR] = tmax[i] if has_tmax else _MISS_T
        w[_MASK] = -1
        w[_MASK + 1] = 0
        w[_FLAGS] = 0
        w[_PRIM] = -1
        w[_GEOM] = -1
        w[_INST] = -1
        _intersect1(scene, address, 0)
        prim[i] = w[_PRIM] if w[_GEOM] != -1 else MISS
        t[i] = f[_TFAR]
        u[i] = f[_U]
        v[i] = f[_V]


@njit(nogil=True, parallel=True, cache=True)
def _trace_parallel(scene, origin, direction, tmax, has_tmax, prim, t, u, v):
    n = origin.shape[0]
    for b in prange((n + _BLOCK - 1) // _BLOCK):
        _trace_range(scene, origin, direction, tmax, has_tmax, b * _BLOCK,
                     min(n, (b + 1) * _BLOCK), prim, t, u, v)


# -- the aggregate -------------------------------------------------------------------
class Accelerator:
    """Closest-hit queries against one triangle set (a whole scene or one
    chunk). Triangle ids returned are indices into `triangles`. Embree reads
    the arrays in place, so this object keeps them alive."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, threads: int = 1):
        self.threads = max(1, int(threads))
        nv, nt = int(len(vertices)), int(len(triangles))
        # Embree reads a vertex with a 16-byte load: one float of padding.
        self._vertices = np.zeros(3 * nv + 1, np.float32)
        self._vertices[:3 * nv] = np.asarray(vertices, np.float32).reshape(-1)
        self._triangles = np.ascontiguousarray(triangles, np.int32)
        self._guard = threading.Lock()
        self._users, self._closing = 0, False
        self._scene = self._build(nv, nt)

    def _build(self, nv: int, nt: int):
        device = _device()
        scene = _LIB.rtcNewScene(device)
        _LIB.rtcSetSceneFlags(scene, _SCENE_FLAG_ROBUST)
        geometry = _LIB.rtcNewGeometry(device, _GEOMETRY_TYPE_TRIANGLE)
        _LIB.rtcSetSharedGeometryBuffer(geometry, _BUFFER_TYPE_VERTEX, 0, _FORMAT_FLOAT3,
                                        self._vertices.ctypes.data, 0, 12, nv)
        _LIB.rtcSetSharedGeometryBuffer(geometry, _BUFFER_TYPE_INDEX, 0, _FORMAT_UINT3,
                                        self._triangles.ctypes.data, 0, 12, nt)
        _LIB.rtcCommitGeometry(geometry)
        _LIB.rtcAttachGeometry(scene, geometry)
        _LIB.rtcReleaseGeometry(geometry)
        _LIB.rtcCommitScene(scene)          # the BVH build, GIL released
        error = _LIB.rtcGetDeviceError(device)
        if error:
            _LIB.rtcReleaseScene(scene)
            raise RuntimeError(f"Embree: building a BVH of {nt} triangles failed (error {error})")
        return scene

    def intersect(self, origin: np.ndarray, direction: np.ndarray,
                  tmax: np.ndarray | None = None):
        """Returns (triangle int32, t float32, u float32, v float32); a miss
        has triangle -1. Rays start at t = 0."""
        n = origin.shape[0]
        origin = np.ascontiguousarray(origin, np.float32)
        direction = np.ascontiguousarray(direction, np.float32)
        has_tmax = tmax is not None
        tmax = np.ascontiguousarray(tmax, np.float32) if has_tmax else np.empty(0, np.float32)
        prim = np.empty(n, np.int32)
        t, u, v = (np.empty(n, np.float32) for _ in range(3))
        scene = self._enter()
        try:
            if self.threads == 1 or n < _MIN_SPLIT:
                _trace_range(scene, origin, direction, tmax, has_tmax, 0, n, prim, t, u, v)
            else:
                numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))
                _trace_parallel(scene, origin, direction, tmax, has_tmax, prim, t, u, v)
        finally:
            self._leave()
        return prim, t, u, v

    def _enter(self) -> int:
        with self._guard:
            if self._scene is None or self._closing:
                raise RuntimeError("Accelerator used after close()")
            self._users += 1
            return self._scene

    def _leave(self) -> None:
        with self._guard:
            self._users -= 1
            if self._closing and self._users == 0:
                self._release()

    def close(self) -> None:
        """Release Embree's BVH and our arrays now, even if a caller still
        holds this object (memory limits count on it). A trace running on
        another thread finishes first; the last one out releases."""
        with self._guard:
            if self._scene is None or self._closing:
                return
            self._closing = True
            if self._users == 0:
                self._release()

    def _release(self) -> None:
        _LIB.rtcReleaseScene(self._scene)
        self._scene = None
        self._vertices = self._triangles = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

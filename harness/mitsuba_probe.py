"""Which Mitsuba variant works on this machine, for the reference renders
(`harness.reference`, which takes the answer as its `variant`).

`llvm_ad_rgb` is about 3x faster than `scalar_rgb`, but a libLLVM that
Mitsuba does not support aborts the whole process while compiling a kernel,
which no exception handler can catch. So the fast variant is first tried in
a child process, once per process; `harness.reference` itself starts none."""
from __future__ import annotations

import functools
import subprocess
import sys

from harness.reference import FAST_VARIANT, SAFE_VARIANT, available_variants

PROBE_TIMEOUT_S = 300

# Renders every plugin kind the translation uses, so a libLLVM that
# miscompiles one of them is caught here rather than killing the caller.
_PROBE = """
import mitsuba as mi
mi.set_variant('llvm_ad_rgb')
d = mi.cornell_box()
d['sensor']['film'].update(width=8, height=8)
d['glass'] = {'type': 'sphere', 'center': [-0.4, -0.6, 0], 'radius': 0.2,
              'bsdf': {'type': 'dielectric', 'int_ior': 1.5}}
d['metal'] = {'type': 'sphere', 'center': [0.4, -0.6, 0], 'radius': 0.2,
              'bsdf': {'type': 'twosided', 'bsdf': {'type': 'roughconductor',
                       'material': 'none', 'alpha': 0.2}}}
d['point'] = {'type': 'point', 'position': [0, 0.5, 0]}
d['spot'] = {'type': 'spot', 'cutoff_angle': 30, 'to_world':
             mi.ScalarTransform4f().look_at([0, 0.5, 1], [0, 0, 0], [0, 1, 0])}
for name in ('path', 'ptracer'):
    d['integrator'] = {'type': name, 'max_depth': 4}
    mi.render(mi.load_dict(d), spp=2).numpy()
print('ok')
"""


@functools.lru_cache(maxsize=1)
def best_variant() -> str:
    """`llvm_ad_rgb` if a child process can render with it, else
    `scalar_rgb`. Raises `ReferenceRenderError` if Mitsuba is missing."""
    if FAST_VARIANT not in available_variants() or not llvm_probe_passes():
        return SAFE_VARIANT
    return FAST_VARIANT


def llvm_probe_passes() -> bool:
    """Whether a child process renders the probe scene with `llvm_ad_rgb`."""
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True,
                              text=True, timeout=PROBE_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0 and done.stdout.strip().endswith("ok")

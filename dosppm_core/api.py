"""The Python API, in the style of Mitsuba 3:

    import dosppm_core as dp

    scene = dp.load("cornell-glass")           # a built-in name, a .toml or .xml file, or a dict
    image = dp.render(scene, seconds=10)       # (height, width, 3) float32 radiance, with .stats
    dp.write("out.exr", image)                 # .exr (linear, float) or .png (tone-mapped)

    big = dp.load("big/")                      # a triangle soup directory or a chunk store
    image = dp.render(big, seconds=60, memory=1 << 30)    # out of core: mode "osppm"

`load` opens what `dosppm render` opens. `render` runs in this process:
mode "sppm" (the whole scene) or "osppm" (the scene cut into chunks, out of
core; the mode of a chunk store, and of a soup, which is cut into chunks
once and kept in the store cache as the command does). The distributed
mode, a server and tracer processes, is the `dosppm render` command: it
needs sockets, which this library does not know.

`render_stops` renders once and hands back the image at several times,
as the evaluation does to chart error against time.
"""
from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING

import numpy as np

from dosppm_core.film import write_exr, write_png
from dosppm_core.modes.deadline import Deadline
from dosppm_core.scene.loaders import load_scene
from dosppm_core.scene.model import Scene, SceneError
from dosppm_core.scene.tomlfile import scene_from_document
from dosppm_core.settings import DEFAULT_BUDGET_BYTES, RenderSettings, default_store_cache, scene_settings

if TYPE_CHECKING:
    from dosppm_core.chunks.store import ChunkStore

MODES = ("sppm", "osppm")
_SETTINGS = {f.name for f in dataclasses.fields(RenderSettings)}


@dataclasses.dataclass(frozen=True)
class Image:
    """A rendered image: `pixels`, linear radiance as (height, width, 3)
    float32, and `stats` (mode, iterations, photons, hit points, seconds).
    numpy and matplotlib take it as the array itself."""
    pixels: np.ndarray
    stats: dict

    def __array__(self, dtype=None, copy=None):
        return self.pixels if dtype is None else self.pixels.astype(dtype)

    @property
    def shape(self) -> tuple:
        return self.pixels.shape


def load(scene: str | os.PathLike | Mapping, width: int | None = None,
         height: int | None = None, **params) -> Scene | "ChunkStore":
    """A scene from a built-in name, a TOML or Mitsuba XML file, or a dict
    with the tables of the TOML format (docs/scene-format.md; mesh files
    relative to the working directory): a `Scene`, in memory. A chunk store
    or a triangle soup directory (`dosppm scenes generate`), too large for
    memory perhaps: a `ChunkStore`, the soup cut into chunks of
    `DEFAULT_BUDGET_BYTES` under `default_store_cache()` the first time (as
    `dosppm render` does). `width`/`height` override the camera's; other
    keywords are a Mitsuba file's `$name` parameters, as in
    `mitsuba.load_file(path, spp=16)`.

    What cannot be opened raises SceneError (a chunk store: StoreError, a
    ValueError) with the one line `dosppm render` prints."""
    if params and (isinstance(scene, Mapping) or not os.fspath(scene).lower().endswith(".xml")):
        raise SceneError(f"parameters {', '.join(params)} given, but only a Mitsuba .xml file takes them")
    if isinstance(scene, Mapping):
        out = scene_from_document(dict(scene), "scene dict", "scene", os.getcwd())
        for key, value in (("width", width), ("height", height)):
            if value:
                setattr(out.camera, key, int(value))
        return out
    spec = os.fspath(scene)
    # Imported here, as below: `import dosppm_core` stays light (no numba, no Embree).
    from dosppm_core.chunks.store import is_store
    from dosppm_core.scene.soupfile import is_soup
    if is_store(spec) or is_soup(spec):
        from dosppm_core.chunks.subdivide import open_render_store
        return open_render_store(spec, default_store_cache(), DEFAULT_BUDGET_BYTES, None, width, height)
    return load_scene(spec, params or None, width=width, height=height)


def render(scene: Scene | "ChunkStore" | str, seconds: float | None = None, *, photons: int | None = None,
           iterations: int | None = None, mode: str | None = None, chunks: int | None = None,
           memory: int | None = None, **settings) -> Image:
    """Render `scene` (what `load` returns, or what it takes) until the
    first limit given is reached: `seconds` of rendering, `photons` emitted
    or `iterations`; with none, 10 seconds. `settings` are RenderSettings
    fields (seed, radius, alpha, direct, gather, photons_per_iteration,
    threads, ...); those not given and fixed by the scene file's integrator
    (a Mitsuba `max_depth`: `settings.scene_settings`) are the file's. `seconds` is a deadline: the image is handed back within
    max(2 s, 5%) of it, with the photons of the work in flight then
    applied or left out whole.

    `mode`: "sppm" for a Scene, "osppm" for a chunk store (the default for
    each). Mode "osppm" cuts a Scene into `chunks` chunks (default 4);
    `memory` bounds its resident chunks in bytes (default: every chunk of
    a Scene; twice the store's budget for a store, as `dosppm render`)."""
    if seconds is None and photons is None and iterations is None:
        seconds = 10.0
    last = None
    for last in _run(scene, mode, chunks, memory, settings, [seconds], photons, iterations):
        pass
    return last


def render_stops(scene: Scene | "ChunkStore" | str, seconds: list[float], *, mode: str | None = None,
                 chunks: int | None = None, memory: int | None = None, **settings) -> Iterator[Image]:
    """One render, its image handed back as each time in `seconds` passes
    (an iteration that spans several times is handed back once, at the last)."""
    yield from _run(scene, mode, chunks, memory, settings, sorted(seconds), None, None)


def write(path: str | os.PathLike, image, exposure: float = 0.0) -> None:
    """An image (an `Image` or an array) as .exr (linear float) or .png
    (sRGB, `exposure` in stops)."""
    path = os.fspath(path)
    rgb = np.asarray(image, dtype=np.float32)
    ext = os.path.splitext(path)[1].lower()
    if ext == ".exr":
        write_exr(path, rgb)
    elif ext == ".png":
        write_png(path, rgb, exposure)
    else:
        raise ValueError(f"{path}: unknown image format {ext!r} (expected .exr or .png)")


# -- the loop -------------------------------------------------------------------------

def _run(scene, mode: str | None, chunks, memory, settings: dict, stops: list, photons,
         iterations) -> Iterator[Image]:
    unknown = sorted(set(settings) - _SETTINGS)
    if unknown:
        raise TypeError(f"unknown render setting {unknown[0]!r} (known: {', '.join(sorted(_SETTINGS))})")
    from dosppm_core.chunks.store import ChunkStore
    scene = scene if isinstance(scene, (Scene, ChunkStore)) else load(scene)
    mode = _mode(scene, mode, chunks)
    # The scene file's integrator (a Mitsuba max_depth) unless the caller says otherwise.
    header = scene if isinstance(scene, Scene) else scene.header
    try:
        settings = {**scene_settings(header.render_settings), **settings}
    except ValueError as exc:
        raise SceneError(f"{header.source}: {exc}") from None
    with tempfile.TemporaryDirectory(prefix="dosppm-api-") as work:
        renderer = _renderer(scene, mode, chunks, memory, RenderSettings(**settings), work)
        try:
            yield from _stops(renderer, mode, stops, photons, iterations)
        finally:
            renderer.close()


def _mode(scene, mode: str | None, chunks) -> str:
    """The mode asked for, or the scene's own: a chunk store renders out of core."""
    chunked = not isinstance(scene, Scene)
    mode = mode or ("osppm" if chunked else "sppm")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)} (the distributed mode is the "
                         f"`dosppm render` command), got {mode!r}")
    if chunked and mode == "sppm":
        raise ValueError(f"{scene.path}: a chunk store renders chunk by chunk: mode 'osppm', not 'sppm'")
    if chunked and chunks is not None:
        raise ValueError(f"{scene.path}: a chunk store is cut into chunks already: drop chunks={chunks}")
    return mode


def _renderer(scene, mode: str, chunks, memory, settings: RenderSettings, work: str):
    if mode == "sppm":
        from dosppm_core.modes.sppm import Renderer
        return Renderer(scene, settings)
    from dosppm_core.chunks.store import ChunkStore
    from dosppm_core.chunks.subdivide import subdivide
    from dosppm_core.modes.osppm import OutOfCoreRenderer
    from dosppm_core.scene.soup import SceneSource
    store = scene
    if isinstance(scene, Scene):
        path = os.path.join(work, "store")
        subdivide(SceneSource(scene), path, chunks=chunks or 4)
        store = ChunkStore.open(path)
    elif memory is None and store.budget_bytes:     # as `dosppm render --mode osppm`
        memory = max(2 * store.budget_bytes, store.chunk_memory.max())
    return OutOfCoreRenderer(store, settings, memory_bytes=memory)


def _stops(renderer, mode: str, stops: list, photons, iterations) -> Iterator[Image]:
    """Iterations until the limits, an image at each time in `stops` (wall
    time from the first iteration, OSPPM's draining of its portal queues
    included); `stats['stop']` is the time it was handed back for. The
    last time is a deadline (dosppm_core/modes/deadline.py)."""
    k, t0 = 0, time.perf_counter()
    deadline = Deadline.after(stops[-1], t0) if stops and stops[-1] is not None else None
    while True:
        p = renderer.run_iteration(deadline)
        elapsed = time.perf_counter() - t0
        done = ((photons is not None and p.photons_emitted >= photons)
                or (iterations is not None and p.iteration >= iterations))
        due = [t for t in stops[k:] if t is not None and elapsed >= t]
        if deadline is not None and not renderer.worth_an_iteration(deadline):
            done, due = True, stops[k:]       # no time for another: this is the last image
        if not (due or done):
            continue
        k += len(due)
        if hasattr(renderer, "finish"):
            renderer.finish(None, deadline)    # OSPPM: trace the photons still queued at portals
        yield _image(renderer, mode, time.perf_counter() - t0, due[-1] if due else None)
        if done or k >= len(stops):
            return


def _image(renderer, mode: str, seconds: float, stop: float | None) -> Image:
    p = renderer.progress()
    stats = {"mode": mode, "iterations": p.iteration, "photons": int(p.photons_emitted),
             "hit_points": int(p.hit_points), "seconds": seconds, "stop": stop}
    return Image(np.array(renderer.image(), dtype=np.float32), stats)


__all__ = ["Image", "MODES", "SceneError", "load", "render", "render_stops", "write"]

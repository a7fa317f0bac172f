"""`dosppm evaluate SUITE`: speed against accuracy, beside other renderers.

Every method renders every scene of a suite on this machine, in one run,
and is stopped at several time budgets; each stop is compared with the
scene's reference image (relMSE, RMSE, mean-luminance bias, and the relMSE
of blurred images, which averages noise away so that mostly bias is left).

Time is render time: scene loading, BVH builds, compiled-kernel loading and
process start are not counted for the in-process methods and Mitsuba
(its scene load neither). The in-process methods are progressive, so one
run is stopped at each budget in turn; Mitsuba renders once per sample
count (1, 2, 4, ... spp); pbrt-v4 (`harness.pbrt`) once per
sample count or SPPM iteration count, each run timed as a whole process
(its start and scene load, about 0.3 s on Sponza, count); DOSPPM runs
`dosppm render --mode dosppm --time T` once per budget, as a user would,
timed as a whole process too (start-up and drain count).

Equal time means equal: the peers' sample counts are calibrated to each
budget by pilot runs (`calibrated`) and DOSPPM's `--time` by its last
run's start-up, and a run that misses its budget by more than 5% runs
again re-sized. One that still misses (a budget shorter than one sample,
or than DOSPPM's start-up) is scored at its measured time, and the
tables say so.

References come from Mitsuba 3 at high sample counts, cached on disk:
`path`, or `ptracer` where a point light's caustic is seen directly (a
path tracer cannot render it), blended per pixel with `path` where the
camera sees a mirror or glass first (which light tracing cannot render).
Where the camera sees a point light's caustic in a mirror, neither
converges; those pixels are left out of the scores above and, where the
case allows it, scored apart against the mirror's limit (`mirror_limit`:
the reflectance times the floor radiance that light tracing renders from
above).

A case may instead take its scene and reference image from the shared
folder (`--shared DIR`, else $DOSPPM_SHARED): `sponza-point`'s reference
is pbrt-v4's. Without the folder
such a case is skipped with its reason, as a missing peer renderer is.
"""
from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import tempfile
import time
import dataclasses
from dataclasses import asdict, dataclass, field, replace

import numpy as np

import dosppm_core as dp
from dosppm_core.accel import Accelerator
from dosppm_core.film import one_line, read_exr
from dosppm_core.kernels.bsdf import is_specular
from dosppm_core.scene import builtin
from dosppm_core.scene.loaders import load_scene
from dosppm_core.scene.model import Scene
from dosppm_core.settings import DIRECT_MODES, RenderSettings
from dosppm_core.trace import eye_ray_job
from harness import metrics, pbrt
from harness.mirror_limit import LimitSettings, mirror_limit
from harness.provenance import provenance
from harness.reference import cached_reference, render_reference
from harness.suites import (CAUSTIC_SCENES, METHODS, SUITES, Case, CaseSkipped, Method, Sample, Suite,
                            shared_dir, shared_file, with_face_normals)

BLUR_SIGMA_PX = 2.0
BUDGET_FRACTIONS = (0.125, 0.25, 0.5, 1.0)

# -- scenes and references ----------------------------------------------------

def suite_scene(suite: Suite, case: Case, shared: str | None = None, work: str | None = None) -> Scene:
    """The case's scene at the suite's resolution; a scene from the shared
    folder keeps its own, which its reference image has. One to be shaded
    flat is read from a copy written into `work` (a new temporary folder
    if None), which `dosppm render` then reads too (`Scene.source`)."""
    if case.files:
        path = shared_file(shared, case.files.scene)
        if case.files.face_normals:
            path = with_face_normals(path, work or tempfile.mkdtemp(prefix="dosppm-flat-"))
        return load_scene(path)
    scene = builtin.make(case.scene)
    scene.camera.width, scene.camera.height = suite.width, suite.height
    return scene


def file_reference(scene: Scene, case: Case, shared: str | None) -> np.ndarray:
    """A case's reference image from the shared folder, checked against the
    scene's resolution."""
    path = shared_file(shared, case.files.reference)
    image = read_exr(path)[0]
    want = (int(scene.camera.height), int(scene.camera.width), 3)
    if image.shape != want:
        raise ValueError(f"{path}: {image.shape[1]}x{image.shape[0]}, but the scene renders "
                         f"{want[1]}x{want[0]}")
    return image


def reference_image(scene: Scene, case: Case, spp: int, cache_dir: str):
    """(image, scored pixels (H, W) bool or None for all): the case's
    Mitsuba reference (cached): `path`, `ptracer`, or the two blended by
    the share of each pixel's eye rays whose first surface is a mirror or
    glass (path there, light tracing elsewhere)."""
    share = None
    if case.reference in ("path", "ptracer"):
        image = cached_reference(scene, spp, cache_dir, integrator=case.reference)
    elif case.reference == "ptracer+path":
        light = cached_reference(scene, spp, cache_dir, integrator="ptracer")
        eye = cached_reference(scene, spp, cache_dir, integrator="path")
        share = specular_first_hit_share(scene)
        image = (share[..., None] * eye + (1.0 - share[..., None]) * light).astype(np.float32)
    else:
        raise ValueError(f"unknown reference {case.reference!r}")
    if case.scored == "all":
        return image, None
    if case.scored == "no-specular-in-view":
        return image, (share if share is not None else specular_first_hit_share(scene)) == 0.0
    raise ValueError(f"unknown pixel selection {case.scored!r}")


def specular_first_hit_share(scene: Scene, rays_per_pixel: int = 64) -> np.ndarray:
    """(H, W): the fraction of a pixel's jittered eye rays whose first
    surface is a mirror or glass (geometry only: no radiance of ours)."""
    w, h = int(scene.camera.width), int(scene.camera.height)
    accel = Accelerator(scene.vertices, scene.triangles)
    try:
        count = np.zeros(w * h)
        for k in range(rays_per_pixel):
            rays = eye_ray_job(scene, 12345, k, 0, w * h)
            prim = accel.intersect(rays.origin, rays.direction)[0]
            hit = prim >= 0
            kinds = scene.materials.kind[scene.tri_material[prim[hit]]]
            count[rays.pixel[hit]] += [bool(is_specular(int(x))) for x in kinds]
    finally:
        accel.close()
    return (count / rays_per_pixel).reshape(h, w)


def mirror_reference(scene: Scene, reference: np.ndarray, scored, cache_dir: str):
    """(reference with the mirror limit in the pixels where the camera sees
    a mirror, those pixels (H, W) bool, a description): the mirror pixels
    are the ones the blended reference leaves unscored."""
    pixels = ~scored if scored is not None else specular_first_hit_share(scene) > 0
    limit = mirror_limit(scene, cache_dir, pixels)
    image = np.where(pixels[..., None], limit.image, reference).astype(np.float32)
    s = LimitSettings()
    about = (f"mirror pixels ({pixels.mean():.0%}): limit, mirror reflectance x the floor "
             f"seen from above by Mitsuba 3 ptracer ({s.floor_resolution}^2, {s.floor_spp} spp), "
             f"{s.rays_per_pixel} eye rays per pixel")
    return image, pixels, about


# -- running the methods --------------------------------------------------------

def method_available(method: Method) -> str | None:
    """None, or why the method is skipped on this machine."""
    if method.kind == "mitsuba":
        try:
            import mitsuba  # noqa: F401 - optional (the [reference] extra)
        except ImportError:
            return "mitsuba is not installed (pip install .[reference])"
    if method.kind == "pbrt":
        return pbrt.missing_reason()
    return None


def run_method(method: Method, scene: Scene, budgets: list[float], seed: int,
               work: str, pbrt_file: str | None = None) -> list[tuple[float, float, int, np.ndarray]]:
    """(budget, seconds, photons, image) at each budget; `pbrt_file` is the
    scene for pbrt-v4 where a case gives one (else `scene` is exported)."""
    if method.kind in ("sppm", "osppm"):
        return _progressive(method, scene, seed, budgets)
    if method.kind == "dosppm":
        return _dosppm(scene, budgets, seed, work)
    if method.kind == "mitsuba":
        return _mitsuba(scene, method.options["integrator"], budgets, seed)
    if method.kind == "pbrt":
        return _pbrt(method, scene, budgets, seed, work, pbrt_file)
    raise ValueError(f"unknown method kind {method.kind!r}")


def _settings(method: Method, seed: int, scene: Scene | None = None) -> RenderSettings:
    s = RenderSettings(seed=seed, gather=method.options.get("gather", "grid"))
    if "radius_of_diagonal" in method.options:
        s.radius = method.options["radius_of_diagonal"] * scene.diagonal()
    for name in ("direct", "max_depth"):    # else RenderSettings' defaults
        if name in method.options:
            setattr(s, name, method.options[name])
    if "resolution" in method.options:
        s.hash_options = {"resolution": tuple(method.options["resolution"])}
    return s


def _progressive(method: Method, scene: Scene, seed: int, budgets):
    """One render through the Python API, its image taken at each budget
    in turn (an iteration that spans several budgets stops once, at the
    last). OSPPM's image is drained of the photons still queued at portals
    at each stop, as `dosppm render` does before it writes (the time counts)."""
    settings = dataclasses.asdict(_settings(method, seed, scene))
    return [(img.stats["stop"], img.stats["seconds"], img.stats["photons"], img.pixels)
            for img in dp.render_stops(scene, budgets, mode=method.kind, chunks=method.options.get("chunks"),
                                       **settings)]


def _mitsuba(scene: Scene, integrator: str, budgets, seed: int):
    """Mitsuba at a sample count calibrated to each budget (`calibrated`),
    each render timed alone, its scene load left out."""
    render_reference(scene, 1, integrator=integrator, seed=seed)   # load and warm up

    def run(spp: int):
        t0 = time.perf_counter()
        image = render_reference(scene, spp, integrator=integrator, seed=seed + spp)
        return time.perf_counter() - t0, 0, image
    return calibrated(run, budgets)


def _pbrt(method: Method, scene: Scene, budgets, seed: int, work: str, pbrt_file: str | None):
    """pbrt-v4 at a sample count (`path`) or iteration count (`sppm`)
    calibrated to each budget (`calibrated`), each run timed as a whole
    process (its start and scene load count)."""
    world = pbrt_file or pbrt.write_scene(scene, tempfile.mkdtemp(prefix="pbrt-", dir=work))
    with open(world, encoding="utf-8") as f:
        text = f.read()
    integrator = method.options["integrator"]
    settings = pbrt.RenderSettings(integrator, 1, int(method.options["max_depth"]),
                                   int(scene.camera.width), int(scene.camera.height),
                                   radius=_pbrt_radius(method, scene),
                                   pixel_filter=pbrt.pixel_filter_line(scene.camera))
    target, run_file = os.path.join(work, "pbrt.exr"), os.path.join(work, "pbrt-run.pbrt")

    def run(samples: int):
        at = replace(settings, samples=samples)
        with open(run_file, "w", encoding="utf-8") as f:
            f.write(pbrt.with_render_settings(text, pbrt.render_directives(at, target),
                                              os.path.dirname(os.path.abspath(world))))
        seconds, image = pbrt.render(run_file, target, seed + samples)
        return seconds, samples * at.photons_per_iteration if integrator == "sppm" else 0, image
    return calibrated(run, budgets)


# A run within this share of its budget counts as at it; tables give the
# measured time of any other (`off_budget`).
ON_BUDGET = 0.05
CALIBRATION_RUNS = 3        # runs per budget at most: the first sized by the pilots, two re-sized


def calibrated(run, budgets) -> list:
    """[(budget, seconds, photons, image)], one run per budget, each of `n`
    samples sized to take the budget: `run(n)` -> (seconds, photons,
    image). Pilots at 1, 2, 4, ... samples, until one takes a tenth of the
    smallest budget (two at least), then every run so far fit seconds = fixed + n x
    per_sample (through the last two sample counts: a secant, so a rate
    that drifts is followed); a run that misses its budget by more than
    ON_BUDGET is re-sized and run again, up to CALIBRATION_RUNS times. The
    last run stands, at its measured time, whether or not it made the
    budget: a single sample may take longer than a small budget."""
    seen = [(1, run(1)[0])]
    while len(seen) < 2 or seen[-1][1] < 0.1 * budgets[0]:
        n = 2 * seen[-1][0]
        seen.append((n, run(n)[0]))
    out = []
    for budget in budgets:
        n = _samples_for(budget, *_fit(seen))
        for _attempt in range(CALIBRATION_RUNS):
            seconds, photons, image = run(n)
            seen.append((n, seconds))
            again = _samples_for(budget, *_fit(seen))
            if not off_budget(budget, seconds) or again == n:
                break
            n = again
        out.append((budget, seconds, photons, image))
    return out


def _fit(seen: list) -> tuple[float, float]:
    """(fixed seconds, seconds per sample) through the last run (n, seconds)
    and the latest before it of another n; with none, all of it per sample."""
    n1, s1 = seen[-1]
    other = next(((n, s) for n, s in reversed(seen) if n != n1), None)
    if other is None:
        return 0.0, max(s1 / n1, 1e-9)
    n0, s0 = other
    per_sample = (s1 - s0) / (n1 - n0)
    if per_sample <= 0:               # noise larger than the difference: the last run's rate alone
        return 0.0, max(s1 / n1, 1e-9)
    return max(s1 - per_sample * n1, 0.0), per_sample


def _samples_for(budget: float, fixed: float, per_sample: float) -> int:
    return max(1, int(round((budget - fixed) / per_sample)))


def off_budget(budget: float, seconds: float) -> bool:
    """Whether a run missed its budget by more than ON_BUDGET."""
    return abs(seconds - budget) > ON_BUDGET * budget


def _pbrt_radius(method: Method, scene: Scene) -> float:
    """pbrt-v4 SPPM's one global initial radius: the method's fraction of
    the scene's diagonal (as our sppm-radius-* methods), else 3 pixel
    footprints; irrelevant to its path tracer."""
    if method.options["integrator"] != "sppm":
        return 1.0
    if "radius_of_diagonal" in method.options:
        return method.options["radius_of_diagonal"] * scene.diagonal()
    return pbrt_sppm_radius(scene)


def pbrt_sppm_radius(scene: Scene, pixels_across: float = 3.0) -> float:
    """pbrt-v4 SPPM's initial radius: `pixels_across` pixel footprints at the
    median distance of the surfaces the camera sees (pbrt's default, 1, is
    in world units whatever the scene's size)."""
    w, h = int(scene.camera.width), int(scene.camera.height)
    rays = eye_ray_job(scene, 12345, 0, 0, w * h)
    accel = Accelerator(scene.vertices, scene.triangles)
    try:
        prim, t = accel.intersect(rays.origin, rays.direction)[:2]
    finally:
        accel.close()
    hit = prim >= 0
    if not hit.any():
        return scene.diagonal() / 100.0
    dist = float(np.median(t[hit] * np.linalg.norm(rays.direction[hit], axis=1)))
    frame = scene.camera.frame()
    if frame[6, 0] > 0:                   # orthographic: a pixel is as wide at any distance
        dist = 1.0
    return pixels_across * 2.0 * float(frame[4, 0]) * dist / w


def _dosppm(scene: Scene, budgets, seed: int, work: str):
    """`dosppm render --mode dosppm` per budget, on the scene's built-in
    name or file, timed as a whole process: its start-up (processes,
    store, kernels) and drain count, as a user waits for them. Its
    `--time` is the budget less what the last run spent beyond its own
    `--time`; a run off its budget by more than ON_BUDGET runs again
    re-sized (up to CALIBRATION_RUNS), and a budget shorter than the
    start-up stands at its measured time."""
    out, beyond = [], 0.0
    spec = scene.source if os.path.isfile(scene.source) else scene.name
    for budget in budgets:
        for _attempt in range(CALIBRATION_RUNS):
            render_s = max(budget - beyond, MIN_DOSPPM_TIME_S)
            seconds, photons, image = _dosppm_run(spec, scene, render_s, seed, work)
            beyond = seconds - render_s
            if not off_budget(budget, seconds) or budget - beyond < MIN_DOSPPM_TIME_S:
                break
        out.append((budget, seconds, photons, image))
    return out


MIN_DOSPPM_TIME_S = 0.25      # the shortest --time asked: below it the start-up is the run


def _dosppm_run(spec: str, scene: Scene, render_s: float, seed: int, work: str):
    """(wall seconds, photons in the image, image) of one `dosppm render`."""
    target = os.path.join(work, f"dosppm-{scene.name}-{render_s:.3f}.exr")
    cmd = [sys.executable, "-m", "services.cli", "render", spec, "--mode", "dosppm",
           "--time", f"{render_s:.3f}", "--seed", str(seed), "--width", str(scene.camera.width),
           "--height", str(scene.camera.height), "--out", target, "--quiet", "--http", "off"]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=render_s * 4 + 120)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"dosppm render failed: {done.stderr.strip().splitlines()[-1:]}")
    with open(os.path.splitext(target)[0] + ".json", encoding="utf-8") as f:
        photons = int(json.load(f)["photons_in_image"])
    return seconds, photons, read_exr(target)[0]


# -- scoring --------------------------------------------------------------------

def score(scene: str, method: str, budget: float, seconds: float, photons: int,
          image: np.ndarray, reference: np.ndarray, scored: np.ndarray | None = None) -> Sample:
    """The sample's errors against `reference` over the `scored` pixels
    (all if None; the blur sees the whole image); a non-finite image is
    recorded as such (its errors stay NaN)."""
    finite = bool(np.isfinite(image).all())
    s = Sample(scene, method, float(budget), float(seconds), int(photons), finite)
    if finite:
        pick = (lambda x: x) if scored is None else (lambda x: x[scored])
        s.relmse = metrics.relmse(pick(image), pick(reference))
        s.rmse = metrics.rmse(pick(image), pick(reference))
        s.mean_luminance = float(np.mean(metrics.luminance(pick(image))))
        if np.mean(metrics.luminance(pick(reference))) > 0:
            s.bias = metrics.mean_luminance_bias(pick(image), pick(reference))
        s.blurred_relmse = metrics.blurred_relmse(image, reference, BLUR_SIGMA_PX, where=scored)
    return s


def score_mirror_limit(s: Sample, image: np.ndarray, limit: np.ndarray,
                       pixels: np.ndarray) -> Sample:
    """Add the errors over the mirror `pixels` against `limit` (the
    reference with the mirror limit there; the blur sees the whole image)."""
    if s.finite:
        s.mirror_limit_relmse = metrics.relmse(image[pixels], limit[pixels])
        s.mirror_limit_blurred_relmse = metrics.blurred_relmse(image, limit, BLUR_SIGMA_PX,
                                                               where=pixels)
        s.mirror_limit_bias = metrics.mean_luminance_bias(image[pixels], limit[pixels])
    return s


@dataclass
class Evaluation:
    suite: str
    budget_s: float
    samples: list = field(default_factory=list)
    skipped: dict = field(default_factory=dict)      # method or scene -> why
    failed: dict = field(default_factory=dict)       # "scene/method" -> error
    references: dict = field(default_factory=dict)   # scene -> description
    images: dict = field(default_factory=dict)       # (scene, method) -> image at full budget
    # Commit, date, machine and command, taken when the run starts: the
    # code that ran, not whatever HEAD is when the results are written.
    provenance: dict = field(default_factory=provenance)


def evaluate(suite: Suite, budget_s: float, methods: list[str] | None = None,
             scenes: list[str] | None = None, cache_dir: str | None = None, seed: int = 1,
             log=print, out_dir: str | None = None, shared: str | None = None) -> Evaluation:
    """Run the suite; `methods` / `scenes` restrict it; `shared` is the
    shared folder (default: `shared_dir()`). With `out_dir`, the results so
    far are written after every scene, so a run that is cut short keeps
    what it measured."""
    cache_dir = cache_dir or os.path.join(os.path.expanduser("~"), ".cache", "dosppm", "references")
    chosen = [METHODS[m] for m in (methods or suite.methods)]
    budgets = [budget_s * f for f in BUDGET_FRACTIONS]
    ev = Evaluation(suite.name, budget_s)
    running = {c.scene for c in suite.cases if not scenes or c.scene in scenes}
    if out_dir:
        carry_over(ev, out_dir, running)
    for m in chosen:
        why = method_available(m)
        if why:
            ev.skipped[m.name] = why
            log(f"skipped {m.name}: {why}")
    _warm_kernels()
    shared = shared_dir(shared)
    with tempfile.TemporaryDirectory(prefix="dosppm-evaluate-") as work:
        for case in suite.cases:
            if case.scene in running:
                _run_case(ev, suite, case, chosen, budgets, seed, work, cache_dir, shared, log)
                if out_dir:
                    write_results(ev, out_dir)
    return ev


def _run_case(ev: Evaluation, suite: Suite, case: Case, chosen: list, budgets: list, seed: int,
              work: str, cache_dir: str, shared: str | None, log) -> None:
    """Every chosen method on one case, scored; a case whose files are
    absent is skipped, a failure recorded, and the suite goes on."""
    try:
        scene = suite_scene(suite, case, shared, work)
        reference, scored, about = case_reference(scene, case, suite, cache_dir, shared, log)
    except CaseSkipped as why:
        ev.skipped[case.scene] = str(why)
        log(f"skipped {case.scene}: {why}")
        return
    except Exception as exc:  # noqa: BLE001 - nothing to score against; the other scenes go on
        _record_failure(ev, f"{case.scene}/reference", exc, log)
        return
    ev.references[case.scene] = about
    ev.images[(case.scene, "reference")] = reference
    limit = _mirror_limit(ev, case, scene, reference, scored, cache_dir, log)
    pbrt_file = _case_pbrt_file(case, shared)
    for m in chosen:
        if m.name in ev.skipped:
            continue
        log(f"{case.scene}: {m.name}")
        try:
            stops = run_method(m, scene, budgets, seed, work, pbrt_file)
            for budget, seconds, photons, image in stops:
                s = score(case.scene, m.name, budget, seconds, photons, image, reference, scored)
                ev.samples.append(s if limit is None else score_mirror_limit(s, image, *limit))
        except Exception as exc:  # noqa: BLE001 - one failing method must not end the suite
            _record_failure(ev, f"{case.scene}/{m.name}", exc, log)
            continue
        if stops:
            ev.images[(case.scene, m.name)] = stops[-1][3]


def case_reference(scene: Scene, case: Case, suite: Suite, cache_dir: str, shared: str | None,
                   log) -> tuple[np.ndarray, np.ndarray | None, str]:
    """(image, scored pixels or None for all, a description): the shared
    folder's image, or Mitsuba's (see `reference_image`)."""
    if case.files:
        log(f"{case.scene}: reference {case.files.reference}")
        return file_reference(scene, case, shared), None, case.files.about
    spp = max(16, int(case.spp * suite.reference_spp_scale))
    log(f"{case.scene}: reference ({case.reference}, {spp} spp)")
    reference, scored = reference_image(scene, case, spp, cache_dir)
    return reference, scored, f"Mitsuba 3 {case.reference}, {spp} spp" + (
        "" if scored is None else f"; {scored.mean():.0%} of pixels scored ({case.scored})")


def _case_pbrt_file(case: Case, shared: str | None) -> str | None:
    """The case's own pbrt-v4 scene, if it has one here (else pbrt renders
    the exported scene)."""
    try:
        return shared_file(shared, case.files.pbrt) if case.files and case.files.pbrt else None
    except CaseSkipped:
        return None


def _record_failure(ev: Evaluation, what: str, exc: BaseException, log) -> None:
    """A failure is recorded in one line and the suite goes on."""
    ev.failed[what] = one_line(exc)
    log(f"{what} failed: {ev.failed[what]}")


def _mirror_limit(ev: Evaluation, case: Case, scene: Scene, reference, scored, cache_dir, log):
    """(limit reference, mirror pixels) for a case that asks for it, else
    None; a failure is recorded and the ordinary scores go on."""
    if not case.mirror_limit:
        return None
    log(f"{case.scene}: mirror limit reference")
    try:
        image, pixels, about = mirror_reference(scene, reference, scored, cache_dir)
    except Exception as exc:  # noqa: BLE001 - the rest of the scene is still scored
        _record_failure(ev, f"{case.scene}/mirror-limit", exc, log)
        return None
    ev.references[case.scene] += f"; {about}"
    ev.images[(case.scene, "mirror limit")] = image
    return image, pixels


def carry_over(ev: Evaluation, out_dir: str, running: set) -> None:
    """Keep the results of scenes this run does not repeat, from an earlier
    run of the same suite and budget into `out_dir` (re-run one scene
    without losing the others)."""
    try:
        with open(os.path.join(out_dir, "results.json"), encoding="utf-8") as f:
            doc = json.load(f)
    except (OSError, ValueError):
        return
    if doc.get("suite") != ev.suite or doc.get("budget_s") != ev.budget_s:
        return
    names = Sample.__dataclass_fields__
    for row in doc.get("samples", []):
        if row.get("scene") not in running:
            ev.samples.append(Sample(**{k: (math.nan if v is None else v)
                                        for k, v in row.items() if k in names}))
    ev.references.update({k: v for k, v in doc.get("references", {}).items() if k not in running})
    ev.failed.update({k: v for k, v in doc.get("failed", {}).items()
                      if k.split("/")[0] not in running})


def read_results(path: str) -> Evaluation:
    """An evaluation back from its results.json (for tables and charts
    made after the run; the images are not kept)."""
    with open(path, encoding="utf-8") as f:
        return read_results_doc(json.load(f))


def read_results_doc(doc: dict) -> Evaluation:
    ev = Evaluation(doc["suite"], doc["budget_s"], references=doc.get("references", {}),
                    skipped=doc.get("skipped", {}), failed=doc.get("failed", {}),
                    provenance=doc.get("provenance") or {"commit": doc.get("commit"), "date": doc.get("date")})
    names = Sample.__dataclass_fields__
    ev.samples = [Sample(**{k: (math.nan if v is None else v) for k, v in row.items() if k in names})
                  for row in doc.get("samples", [])]
    return ev


def _warm_kernels() -> None:
    """Compile (or load) the numba kernels, the chunked ones included, for
    either kind of direct light and gather, before any clock starts."""
    scene = builtin.make("cornell-box")
    scene.camera.width = scene.camera.height = 8
    for direct in DIRECT_MODES:
        for gather in ("grid", "hash"):
            for mode in ("sppm", "osppm"):
                dp.render(scene, iterations=1, mode=mode, chunks=4, direct=direct, gather=gather,
                          photons_per_iteration=2000)


# -- output ---------------------------------------------------------------------

def write_results(ev: Evaluation, out_dir: str) -> list[str]:
    """results.json, results.csv, summary.md and, with matplotlib, the
    charts. Returns the paths written."""
    os.makedirs(out_dir, exist_ok=True)
    rows = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v)
             for k, v in asdict(s).items()} for s in ev.samples]
    doc = {"suite": ev.suite, "budget_s": ev.budget_s, "provenance": ev.provenance,
           "commit": ev.provenance["commit"], "date": ev.provenance["date"],
           "references": ev.references, "skipped": ev.skipped, "failed": ev.failed,
           "methods": {m: METHODS[m].about for m in {r["method"] for r in rows}},
           "samples": rows}
    paths = [os.path.join(out_dir, "results.json"), os.path.join(out_dir, "results.csv"),
             os.path.join(out_dir, "summary.md")]
    with open(paths[0], "w", encoding="utf-8") as f:
        json.dump(doc, f, indent=1, allow_nan=False)
    with open(paths[1], "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=list(Sample.__dataclass_fields__))
        writer.writeheader()
        writer.writerows(rows)
    with open(paths[2], "w", encoding="utf-8") as f:
        f.write(summary_markdown(ev))
    try:   # the charts need matplotlib, an optional dependency (the [bench] extra)
        from harness import charts as evaluate_charts
    except ImportError as exc:
        print(f"charts skipped: {exc}", file=sys.stderr)
    else:
        paths += evaluate_charts.write_charts(ev, out_dir)
    return paths


def final_samples(ev: Evaluation, budget_s: float | None = None) -> dict:
    """(scene, method) -> the sample at the largest budget (or at the
    budget `budget_s`: the last run filed under it)."""
    best = {}
    for s in ev.samples:
        key = (s.scene, s.method)
        if budget_s is not None and s.budget_s != budget_s:
            continue
        if key not in best or s.budget_s >= best[key].budget_s:
            best[key] = s
    return best


def relmse_table(ev: Evaluation, budget_s: float | None = None, methods: list | None = None) -> list[str]:
    """Markdown rows: per scene and method, relMSE with the mean-luminance
    bias (or the mean luminance Y where the reference is black) at the
    last budget or at `budget_s`."""
    last = final_samples(ev, budget_s)
    methods = methods or list(dict.fromkeys(s.method for s in ev.samples))
    lines = ["| scene | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for scene in _scene_order(ev):
        cells = []
        for m in methods:
            s = last.get((scene, m))
            cells.append("-" if s is None else "!" if not s.finite else
                         (f"{s.relmse:.3g} ({s.bias:+.1%})" if math.isfinite(s.bias) else
                          f"{s.relmse:.3g} (Y {s.mean_luminance:.2g})") + _measured(s))
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    return lines


def _measured(s: Sample) -> str:
    """' at T s' for a run that missed its budget by more than ON_BUDGET
    (`calibrated`): its score is at that time, not the budget's."""
    return f" at {s.seconds:.1f} s" if off_budget(s.budget_s, s.seconds) else ""


def summary_markdown(ev: Evaluation) -> str:
    last = final_samples(ev)
    methods = list(dict.fromkeys(s.method for s in ev.samples))
    lines = [f"relMSE at {ev.budget_s:g} s of render time (suite `{ev.suite}`), with the "
             "mean-luminance bias, or the mean luminance Y where the reference is black "
             "(light that leaked); ! = a non-finite pixel; 'at T s': a run that missed the budget by "
             f"more than {ON_BUDGET:.0%}, scored at its measured time", "", *relmse_table(ev, None, methods)]
    lines += mirror_limit_table(ev, last, methods)
    lines += ["", *claims(ev)]
    if ev.skipped:
        lines += ["", "Skipped: " + "; ".join(f"{m} ({why})" for m, why in ev.skipped.items())]
    if ev.failed:
        lines += ["", "Failed: " + "; ".join(f"{k} ({why})" for k, why in ev.failed.items())]
    return "\n".join(lines) + "\n"


def mirror_limit_table(ev: Evaluation, last: dict, methods: list) -> list[str]:
    """The pixels where the camera sees a mirror, against the mirror's limit
    reference: relMSE, blurred relMSE and bias at the last stop."""
    scenes = [sc for sc in _scene_order(ev)
              if any(math.isfinite(s.mirror_limit_relmse) for k, s in last.items() if k[0] == sc)]
    if not scenes:
        return []
    lines = ["", f"Mirror pixels against the mirror limit at {ev.budget_s:g} s: relMSE / "
             f"blurred relMSE ({BLUR_SIGMA_PX:g} px) (mean-luminance bias)", "",
             "| scene | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for scene in scenes:
        cells = []
        for m in methods:
            s = last.get((scene, m))
            cells.append("-" if s is None or not math.isfinite(s.mirror_limit_relmse) else
                         f"{s.mirror_limit_relmse:.3g} / {s.mirror_limit_blurred_relmse:.3g} "
                         f"({s.mirror_limit_bias:+.1%})")
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    return lines


def claims(ev: Evaluation) -> list[str]:
    """The issue's two claims as measured: SPPM against Mitsuba `path` at
    equal time, on the caustic scenes and the others; where the reference
    is black (a dark room behind a thin wall), the light each leaked. Then
    SPPM against pbrt-v4's SPPM where both ran."""
    last = final_samples(ev)
    return _mitsuba_claims(ev, last) + _pbrt_claims(ev, last)


def _pbrt_claims(ev: Evaluation, last: dict) -> list[str]:
    out = []
    for scene in _scene_order(ev):
        ours, peer = last.get((scene, "sppm-grid")), last.get((scene, "pbrt-sppm"))
        if not (ours and peer and ours.finite and peer.finite and ours.relmse > 0):
            continue
        out.append(f"- {scene}: pbrt-v4 sppm relMSE / SPPM grid relMSE = "
                   f"{peer.relmse / ours.relmse:.3g}; mean bias SPPM grid {ours.bias:+.1%}, "
                   f"pbrt-v4 sppm {peer.bias:+.1%}{_times(ours, peer)}")
    return out


def _mitsuba_claims(ev: Evaluation, last: dict) -> list[str]:
    out = []
    for scene in _scene_order(ev):
        ours, path = last.get((scene, "sppm-grid")), last.get((scene, "mitsuba-path"))
        if not (ours and path and ours.finite and path.finite):
            continue
        if not math.isfinite(ours.bias):
            out.append(f"- {scene} (black reference): mean luminance leaked, SPPM grid "
                       f"{ours.mean_luminance:.2g}, Mitsuba path {path.mean_luminance:.2g}")
            continue
        ratio = path.relmse / ours.relmse if ours.relmse > 0 else math.inf
        kind = "caustic" if scene in CAUSTIC_SCENES else "other"
        out.append(f"- {scene} ({kind}): Mitsuba path relMSE / SPPM grid relMSE = {ratio:.3g} "
                   f"({'SPPM lower' if ratio > 1 else 'path lower'}){_times(ours, path)}")
    return out


def _times(a: Sample, b: Sample) -> str:
    """Where either of a compared pair missed its budget, both measured
    times: the ratio is then not at equal time."""
    if not (off_budget(a.budget_s, a.seconds) or off_budget(b.budget_s, b.seconds)):
        return ""
    return f" (not at equal time: {a.seconds:.1f} s against {b.seconds:.1f} s)"


def _scene_order(ev: Evaluation) -> list[str]:
    """The scenes with samples, in the suite's order."""
    order = [c.scene for c in SUITES[ev.suite].cases] if ev.suite in SUITES else []
    seen = list(dict.fromkeys(s.scene for s in ev.samples))
    return [s for s in order if s in seen] + [s for s in seen if s not in order]

"""The render loop: samples -> camera rays -> trace -> pixel estimates, in chunks of whole pixels.

Pixels are visited in screen tiles (`TILE` × `TILE`, row by row inside a tile) with all samples of a pixel
next to each other, so consecutive rays are neighbours on the screen: the scene's packet culling then sees
coherent packets. Every pixel lies in exactly one chunk, so its estimate is a sum over its own samples and
the image does not depend on the chunk size.
"""
from __future__ import annotations

import atexit
import concurrent.futures
import contextlib
import functools
import hashlib
import math
import multiprocessing
import os
import pickle
import sys
import threading
import time
import warnings
from dataclasses import dataclass, replace

import torch

from renderer.tracing.integrator import trace
from camio.interrupts import INTERRUPTS, held
from camio.progress import Progress
from renderer.tracing.sampling import Sampler, camera_samples
from renderer.scene.model import Scene, TraceOptions, compiled_call

# Side of the square screen tiles, pixels.
TILE = 8


@dataclass
class RenderResult:
    """image: (H, W, 3) linear RGB; coverage: (H, W) fraction of a pixel's samples that had a valid ray;
    not_mapped: what another renderer (`--backend mitsuba`) could not reproduce of the scene or options."""

    image: torch.Tensor
    coverage: torch.Tensor
    not_mapped: tuple[str, ...] = ()


def render_passes(scene: Scene):
    """(camera, first-hit object flags or None) from the lowest to the highest priority.

    Without layers this is the scene camera seeing everything. With layers, objects in no layer form a
    default perspective layer drawn first; each layer then overwrites the pixels its first ray hits.
    """
    if not scene.layers:
        return [(scene.camera, None)]
    assigned = set()
    passes = []
    for layer in sorted(scene.layers, key=lambda l: l.priority):
        assigned.update(layer.object_ids)
        flags = [i in layer.object_ids for i in range(len(scene.objects))]
        passes.append((layer.camera, flags))
    rest = [i not in assigned for i in range(len(scene.objects))]
    if any(rest):
        passes.insert(0, (scene.camera, rest))
    return passes


def tile_order(width: int, height: int, tile: int = TILE) -> torch.Tensor:
    """(W·H,) long pixel indices (row · W + column) in tile order: tiles of tile × tile pixels left to right,
    top to bottom, and the pixels of a tile row by row (edge tiles are cut to the image)."""
    y, x = torch.arange(height)[:, None], torch.arange(width)[None, :]
    tiles_x = -(-width // tile)
    key = ((y // tile) * tiles_x + x // tile) * tile * tile + (y % tile) * tile + x % tile
    return torch.argsort(key.reshape(-1))


@functools.lru_cache(maxsize=4)
def _tile_order_cached(width: int, height: int) -> torch.Tensor:
    """`tile_order`, kept for the next render of the same size (about 10 ms at 512×512; only sliced, never
    written to)."""
    return tile_order(width, height)


def _pixel_estimates(color, weight, valid, background, spp: int, all_valid: bool = False):
    """Weighted mean of each pixel's spp consecutive samples (n, 3) (background where no sample has
    weight), and the fraction of valid samples (n,). all_valid: the caller knows every sample is valid."""
    w = weight if all_valid else torch.where(valid, weight, torch.zeros_like(weight))
    if color.T.is_contiguous() and not color.is_contiguous():  # a view of (3, n·spp) rows (renderer.tracing.direct)
        acc = (color.T * w).view(3, -1, spp).sum(-1).T
    else:
        acc = (color * w[:, None]).reshape(-1, spp, 3).sum(1)
    wsum = w.view(-1, spp).sum(1)
    estimate = torch.where((wsum > 0)[:, None], acc / wsum.clamp_min(1e-30)[:, None], background)
    if all_valid:
        return estimate, torch.ones(wsum.shape, dtype=color.dtype, device=color.device)
    return estimate, valid.view(-1, spp).sum(1).to(color.dtype) / spp


def _render_pixels(scene: Scene, pixel: torch.Tensor, sampler: Sampler, options: TraceOptions, device, dtype,
                   max_depth: int | None):
    """Estimates (n, 3) and coverage (n,) of the pixels `pixel` (n,), traced as one batch of n·spp rays.

    `pixel` may repeat its last entry to fill whole culling packets; the repeats are traced and dropped by
    the caller.
    """
    spp, W = sampler.spp, scene.camera.width
    if options.intersector == "mitsuba":
        from renderer.tracing import fused, jit_direct

        if jit_direct.applies(scene, options, device, dtype):  # the whole batch in Dr.Jit kernels beside Embree
            return jit_direct.render_pixels(scene, pixel, sampler, options)
        if fused.applies(scene, options, device, dtype):  # compiled stages between the Embree calls
            return fused.render_pixels(scene, pixel, sampler, options)
    background = torch.tensor(scene.image.background, dtype=dtype, device=device)
    # Samples are made where they are traced: integer hashing and exact float steps give the same values on
    # every device, and on a GPU this saves the host-side sampling and its copy (docs/speed.md).
    uv_px, lens_uv = camera_samples(sampler, pixel.to(device), W, dtype)
    color = weight = valid = None
    all_valid = False
    for camera, flags in render_passes(scene):
        rays = compiled_call(options.compile, type(camera).generate_rays, camera, uv_px, lens_uv)
        rad, found = trace(scene, rays.origin, rays.direction, flags, max_depth, options=options)
        take = rays.valid if flags is None else rays.valid & found
        every = color is None and bool(take.all())
        if every:
            color = rad
        else:
            base = background.expand_as(rad) if color is None else color
            color = torch.where(take[:, None], rad, base)
        if weight is None:
            weight, valid = rays.weight, rays.valid
            all_valid = every and flags is None  # take was rays.valid
    return compiled_call(options.compile, _pixel_estimates, color, weight, valid, background, spp, all_valid)


def _chunks(scene: Scene, spp: int, options: TraceOptions, chunk_rays: int):
    """(pixels, n) per chunk: whole pixels in tile order, padded to whole culling packets by repeating the
    last pixel; n is the number of real pixels."""
    W, H = scene.camera.width, scene.camera.height
    order = _tile_order_cached(W, H)
    step = _packet_step(options, spp)
    pixels_per_chunk = _pixels_per_chunk(options, spp, chunk_rays)
    for start in range(0, W * H, pixels_per_chunk):
        pixel = order[start:start + pixels_per_chunk]
        n = pixel.shape[0]
        if n % step:
            pixel = torch.cat([pixel, pixel[-1:].expand(step - n % step)])
        yield pixel, n


def _packet_step(options: TraceOptions, spp: int) -> int:
    """Pixels whose samples fill whole culling packets: chunks are multiples of it."""
    packet = max(1, options.packet_size)
    return packet // math.gcd(packet, spp)


def _pixels_per_chunk(options: TraceOptions, spp: int, chunk_rays: int) -> int:
    """Whole pixels in a batch of about chunk_rays rays, a multiple of `_packet_step`."""
    step = _packet_step(options, spp)
    return max(step, chunk_rays // spp // step * step)


_POOL: dict = {}  # number of workers -> ProcessPoolExecutor, kept for later renders
# Jobs per worker process in a render: each job ships the pickled scene and returns its pixels, so jobs are
# few and large (a worker traces its job in chunk_rays batches); several per worker keep the cores busy to the
# end (docs/speed.md, "Defaults and where they come from").
JOBS_PER_WORKER = 4
# ... and at most this many rays a job (8 batches of 2^17), so that big renders show progress and stop on an
# interrupt within about a second a job.
MAX_JOB_RAYS = 1 << 20


def _job_rays(scene, spp: int, workers: int, chunk_rays: int) -> int:
    """Camera rays per worker job: JOBS_PER_WORKER jobs a worker, at most MAX_JOB_RAYS, at least a batch."""
    rays = scene.camera.width * scene.camera.height * spp
    return max(chunk_rays, min(MAX_JOB_RAYS, -(-rays // (JOBS_PER_WORKER * workers))))


# How often a worker process checks that its parent still runs, and the parent waiting for the workers wakes
# to act on a SIGINT or SIGTERM sent to it alone (seconds; otherwise it is acted on when a job finishes).
PARENT_CHECK_S = 1.0


def _worker_start(parent_pid: int | None = None):
    # One thread per process: the processes share the cores instead of torch's threads.
    torch.set_num_threads(1)
    if parent_pid is not None:
        threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True, name="parent-watch").start()


def _exit_with_parent(parent_pid: int) -> None:
    """A worker's watchdog: end this process once its parent is gone (a SIGKILLed `renderer render` would
    otherwise leave its workers running, each holding its scene, until ended by hand)."""
    while True:
        if os.getppid() != parent_pid:
            os._exit(1)
        time.sleep(PARENT_CHECK_S)


_WORKER_SCENE: dict = {}  # in a worker: digest of the pickled scene -> the scene, kept while it is reused


def _worker_render(digest, blob, pixel, n, spp, sampler, seed, options, dtype, max_depth, chunk_rays, jit_runs):
    """One job in a worker: the pixels `pixel` (padded to whole packets) traced in chunk_rays batches.
    jit_runs: the parent found Mitsuba's llvm variant running here (the worker need not probe it again)."""
    if digest not in _WORKER_SCENE:  # unpickle once per render, so caches and compiled state are reused
        _WORKER_SCENE.clear()
        _WORKER_SCENE[digest] = pickle.loads(blob)
    scene = _WORKER_SCENE[digest]
    if options.intersector == "mitsuba":  # one Dr.Jit thread per worker, as one torch thread
        from renderer.mitsuba.variants import variant_runs
        from renderer.mitsuba.intersect import DEFAULT_VARIANT, set_jit_threads

        if jit_runs:
            variant_runs(DEFAULT_VARIANT)
        set_jit_threads(1)
    return _trace_job(scene, pixel, n, Sampler(sampler, spp, seed), options, dtype, max_depth, chunk_rays)


def _trace_job(scene, pixel, n, smp, options, dtype, max_depth, chunk_rays):
    """Estimates (n, 3) and coverage (n,) of the first n of the pixels `pixel` (padded to whole packets),
    traced on the CPU in chunk_rays batches: one job of a worker."""
    sub = _pixels_per_chunk(options, smp.spp, chunk_rays)
    parts = [_render_pixels(scene, pixel[a:a + sub], smp, options, "cpu", dtype, max_depth)
             for a in range(0, pixel.shape[0], sub)]
    estimate, covered = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    return estimate[:n].clone(), covered[:n].clone()


# `workers=None` (the default) starts worker processes for renders of at least this many camera rays (512×512
# at 4 spp): below it, starting the pool (about 1-2 s once per process) and shipping the scene to it cost
# more than the second core gains.
AUTO_WORKERS_MIN_RAYS = 1 << 20
_AUTO_WORKERS_OFF: list = []  # why `workers=None` stopped starting processes in this process, once it had to


def _cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def _spawn_safe() -> bool:
    """Whether worker processes may start. `spawn` runs the main script (or `-m` module) again in each
    worker, so a render reached from its top level must sit under `if __name__ == "__main__":`, else every
    worker would run the script. True: an interactive session or notebook (no main file); `python -m
    package` (spawn skips a package's `__main__`); a call from inside that guard; a call not from the main
    module's top level (later, e.g. from a thread: `render` still stops a worker's rerun, see `render`).
    False: a script read from stdin (a worker cannot load it); a call from a script's unguarded top level."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    spec = getattr(main, "__spec__", None)
    if path is None or (spec is not None and spec.name.endswith(".__main__")):
        return True  # nothing to run again; `python -m package`: spawn skips a package's __main__
    if not os.path.exists(path):
        return False
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_globals is vars(main) and frame.f_code.co_name == "<module>":
            return any(a <= frame.f_lineno <= b for a, b in _main_guards(path))
        frame = frame.f_back
    return True


@functools.lru_cache(maxsize=None)
def _main_guards(path: str) -> list[tuple[int, int]]:
    """(first, last) lines of the top-level `if __name__ == "__main__":` blocks of the Python file `path`, as
    first read in this process: a script edited while it runs (its lines moving under the running frame)
    keeps its workers (a benchmark edited mid-run had fallen back to one process)."""
    import ast

    try:
        with open(path, "rb") as f:
            tree = ast.parse(f.read())
    except (OSError, SyntaxError, ValueError):
        return []
    main_test = {("__name__", "__main__"), ("__main__", "__name__")}

    def side(node):
        return node.id if isinstance(node, ast.Name) else node.value if isinstance(node, ast.Constant) else None

    return [(node.lineno, node.end_lineno) for node in tree.body
            if isinstance(node, ast.If) and isinstance(node.test, ast.Compare) and len(node.test.ops) == 1
            and isinstance(node.test.ops[0], ast.Eq)
            and (side(node.test.left), side(node.test.comparators[0])) in main_test]


def auto_workers(scene: Scene, rays: int, device, dtype) -> int:
    """How many worker processes trace with `workers=None`: the cores this process may run on, for a
    float32 CPU render of at least `AUTO_WORKERS_MIN_RAYS` camera rays of a scene without tensors that need
    gradients (workers return no graph), from a process that is not itself a multiprocessing child, where
    starting workers is safe (`_spawn_safe`: not from a script's top level outside
    `if __name__ == "__main__":`); 1 otherwise, and from the time worker processes once failed to start
    here (see `render`). The image does not depend on it."""
    if (torch.device(device).type != "cpu" or dtype != torch.float32 or rays < AUTO_WORKERS_MIN_RAYS
            or _AUTO_WORKERS_OFF or multiprocessing.parent_process() is not None or not _spawn_safe()):
        return 1
    return 1 if scene.requires_grad() else _cores()


def _resolve_intersector(scene: Scene, options: TraceOptions, device, dtype) -> TraceOptions:
    """options with `intersector="auto"` made `mitsuba` or `torch` for this render, so that workers and the
    thread settings see what will answer (see `renderer.mitsuba.intersect.auto_engine`)."""
    if options.intersector != "auto":
        return options
    from renderer.mitsuba.intersect import auto_engine

    return replace(options, intersector="torch" if auto_engine(scene, device, dtype) is None else "mitsuba")


def _shutdown_pools():
    """Stop the worker processes at exit (before the interpreter tears down the modules their threads use)."""
    for pool in _POOL.values():
        pool.shutdown(wait=True, cancel_futures=True)
    _POOL.clear()


def _pool(workers: int):
    if not _POOL:
        atexit.register(_shutdown_pools)
    if workers not in _POOL:
        context = multiprocessing.get_context("spawn")  # forking a process with torch's threads can hang
        _POOL[workers] = concurrent.futures.ProcessPoolExecutor(workers, mp_context=context,
                                                                initializer=_worker_start,
                                                                initargs=(os.getpid(),))
    return _POOL[workers]


# Rays a batch: on the CPU, larger batches pay Python's per-operation cost less often; on a GPU, kernel
# launches are paid per batch; with Embree (`intersector="mitsuba"`), Dr.Jit's per-call costs (tracing its IR,
# handing arrays over). Each the fastest measured on the speed scene (docs/speed.md, "Defaults and where they
# come from").
CPU_CHUNK_RAYS, GPU_CHUNK_RAYS = 1 << 17, 1 << 22
MIN_GPU_CHUNK_RAYS = 1 << 15
EMBREE_CHUNK_RAYS = 1 << 17
BYTES_PER_RAY = 2048  # twice the measured ~1 KB a ray (float32, depth 5); the batch takes at most half the
                     # free memory: room for float64 and for torch's cached blocks


def default_chunk_rays(device) -> int:
    """Rays traced at once by default: 2^17 on the CPU; on a GPU 2^22 (launch overhead amortised), fewer
    (down to 2^15) where the device's free memory would not hold them."""
    device = torch.device(device)
    if device.type != "cuda":
        return CPU_CHUNK_RAYS
    free, _ = torch.cuda.mem_get_info(device)
    # Blocks torch holds in its cache are free to this render too (mem_get_info does not count them).
    free += torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)
    return int(max(MIN_GPU_CHUNK_RAYS, min(GPU_CHUNK_RAYS, free // (2 * BYTES_PER_RAY))))


def render(scene: Scene, spp: int | None = None, sampler: str | None = None, *, device="cpu",
           dtype=torch.float32, seed: int = 0, chunk_rays: int | None = None, progress: bool = False,
           max_depth: int | None = None, culling: bool | None = None, compile: bool | None = None,
           workers: int | None = None, threads: int | None = 1, intersector: str | None = None) -> RenderResult:
    """Render the scene's camera image.

    Args:
        spp: samples per pixel [scene.image.spp]; sampler: `independent`, `stratified`, `sobol` or
            `center` [scene.image.sampler]; seed: of the samples (the same seed, the same image) [0].
        device, dtype: where and in what precision to trace (float32 for speed, float64 for checks).
        chunk_rays: camera samples traced at once (rounded to whole pixels); bounds memory (about 1 KB per
            ray at depth 5). The image does not depend on it. [`default_chunk_rays`: `CPU_CHUNK_RAYS` on the
            CPU, `GPU_CHUNK_RAYS` on a GPU or fewer where its free memory is short; `EMBREE_CHUNK_RAYS` with
            `intersector="mitsuba"`, `jit_direct.CHUNK_RAYS` on its Dr.Jit path, `fused.CHUNK_RAYS` on the
            fused path]
        progress: print the progress on stderr [False]; max_depth: bounces [scene.image.max_depth].
        culling, compile, intersector: override scene.options (see `renderer.scene.model.TraceOptions`); speed only.
            `intersector="mitsuba"`: hits and shadow rays by Embree through Mitsuba 3
            (`renderer.mitsuba.intersect`), float32 images the same as ours to float rounding (a ray grazing
            an edge may change its hit); the default `auto` takes it for float32 CPU renders where Mitsuba's
            llvm variant loads and every shape is one it has, ours otherwise; `torch`: always ours.
            With it, where `renderer.tracing.jit_direct.applies` (direct light, thin lens, CPU float32, not
            compile; the speed scene's kind), the whole batch runs as Dr.Jit kernels beside Embree
            (milliseconds of compilation, kept on disk by Dr.Jit).
            `compile=True` with `intersector="mitsuba"`: where `renderer.tracing.fused.applies` (direct light, thin
            lens, CPU float32), the work between the Embree calls runs as three compiled stages (seconds of
            compilation per process and batch size).
        workers: CPU only: trace chunks in this many worker processes with one torch thread each (they
            are started on first use and kept for later calls; each unpickles the scene once per render).
            The image does not depend on it. None (the default): `auto_workers`, i.e. the available cores
            for float32 CPU renders of at least `AUTO_WORKERS_MIN_RAYS` camera rays without gradients, else
            1; on the Dr.Jit path (`jit_direct`) none: Dr.Jit's thread pool runs its kernels on the
            available cores in this process, as Mitsuba's renders do. Processes are started with `spawn`, which runs the main script again in each worker, so a
            script's renders get workers only from inside `if __name__ == "__main__":` (a render at a
            script's unguarded top level traces in its own process); where workers still fail to start,
            `render` warns once and traces in this process from then on.
        threads: torch threads while tracing on the CPU in this process, restored afterwards [1; None:
            torch's own setting]; with `intersector="mitsuba"` Dr.Jit's thread pool gets the same number
            while tracing (on the Dr.Jit path with `workers=None`, the available cores). Eager tracing is a
            chain of small memory-bound operations, and threads of one process wait on each other where
            other programs share the cores: use `workers` for more cores (measurements in docs/speed.md).
    Returns:
        RenderResult with the (H, W, 3) image and the (H, W) coverage; pixels without any valid ray keep
        the background colour.
    """
    W, H = scene.camera.width, scene.camera.height
    spp = scene.image.spp if spp is None else spp
    sampler = sampler or scene.image.sampler
    scene.refresh()  # a shape moved or replaced since the last render: culling spheres, extent, materials
    options = _options(scene, culling, compile, intersector, device, dtype)
    chunk_rays = _chunk_size(scene, options, chunk_rays, device, dtype)
    auto = workers is None
    if auto and _jit_kernels(scene, options, device, dtype):
        workers, jit_threads = 1, _cores()  # Dr.Jit's own pool runs the kernels on every core, as Mitsuba's does
    else:
        workers = _worker_count(scene, workers, W * H * spp * len(render_passes(scene)), device, dtype)
        jit_threads = threads if options.intersector == "mitsuba" and workers <= 1 else None
    smp = Sampler(sampler, spp, seed)
    image = torch.empty(W * H, 3, dtype=dtype, device=device)
    coverage = torch.empty(W * H, dtype=dtype, device=device)
    bar = Progress(W * H * spp, "render", enabled=progress)
    with _thread_limits(threads, device, jit_threads):
        _render_into(scene, image, coverage, bar, spp, sampler, smp, options, device, dtype, seed, chunk_rays,
                     max_depth, workers, auto)
    return RenderResult(image.reshape(H, W, 3), coverage.reshape(H, W))


def _options(scene: Scene, culling, compile, intersector, device, dtype) -> TraceOptions:
    """scene.options with the caller's culling, compile and intersector where given, `auto` resolved."""
    options = scene.options
    if culling is not None:
        options = replace(options, culling=culling)
    if compile is not None:
        options = replace(options, compile=compile)
    if intersector is not None:
        options = replace(options, intersector=intersector)
    return _resolve_intersector(scene, options, device, dtype)


def _jit_kernels(scene: Scene, options: TraceOptions, device, dtype) -> bool:
    """Whether the render's batches are traced as Dr.Jit kernels (`renderer.tracing.jit_direct`)."""
    if options.intersector != "mitsuba":
        return False
    from renderer.tracing import jit_direct

    return jit_direct.applies(scene, options, device, dtype)


def _chunk_size(scene: Scene, options: TraceOptions, chunk_rays: int | None, device, dtype) -> int:
    """Camera rays a batch: chunk_rays where given; else `jit_direct.CHUNK_RAYS` on the Dr.Jit path,
    `fused.CHUNK_RAYS` on the fused path, `EMBREE_CHUNK_RAYS` with the mitsuba intersector,
    `default_chunk_rays` otherwise."""
    if chunk_rays is not None:
        return chunk_rays
    if options.intersector != "mitsuba":
        return default_chunk_rays(device)
    if _jit_kernels(scene, options, device, dtype):
        from renderer.tracing import jit_direct

        return jit_direct.CHUNK_RAYS
    if options.compile:
        from renderer.tracing import fused

        if fused.applies(scene, options, device, dtype):
            return fused.CHUNK_RAYS
    return EMBREE_CHUNK_RAYS


def _worker_count(scene: Scene, workers: int | None, rays: int, device, dtype) -> int:
    """workers where given, else `auto_workers` for `rays` camera rays; refuses to run in a worker process
    that is starting (it re-runs the main script)."""
    if workers is not None:
        return workers
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        # A worker process starting for `workers=None` re-runs the main script: stop it at its first render.
        raise RuntimeError("render: called while a worker process starts and runs the main script again; guard "
                           "the script's work with `if __name__ == \"__main__\":` or pass workers=1")
    return auto_workers(scene, rays, device, dtype)


@contextlib.contextmanager
def _thread_limits(threads: int | None, device, jit_threads: int | None):
    """torch's CPU threads set to `threads` and Dr.Jit's thread pool to `jit_threads` inside the block, both
    restored after it; None: left as they are."""
    previous = torch.get_num_threads()
    if threads is not None and torch.device(device).type == "cpu" and threads != previous:
        torch.set_num_threads(threads)
    jit_previous = None
    if jit_threads is not None:
        from renderer.mitsuba.intersect import set_jit_threads

        jit_previous = set_jit_threads(jit_threads)
    try:
        yield
    finally:
        if torch.get_num_threads() != previous:
            torch.set_num_threads(previous)
        if jit_previous is not None:
            set_jit_threads(jit_previous)

def _render_into(scene, image, coverage, bar, spp, sampler, smp, options, device, dtype, seed, chunk_rays,
                 max_depth, workers, auto=False):
    """The chunk loop of `render`, filling image (W·H, 3) and coverage (W·H,) in place. auto: `workers` was
    chosen by `auto_workers`; where the workers cannot take the scene or do not start, trace here instead."""
    blob = None
    if workers > 1 and torch.device(device).type == "cpu":
        try:
            blob = pickle.dumps(scene)
        except Exception:  # noqa: BLE001 - e.g. a user's lambda in the scene; auto keeps to this process
            if not auto:
                raise
    if blob is not None:
        from renderer.mitsuba.intersect import llvm_available

        pool = _pool(workers)
        digest = hashlib.sha1(blob).hexdigest()
        jit_runs = options.intersector == "mitsuba" and llvm_available()
        job_rays = _job_rays(scene, spp, workers, chunk_rays)
        jobs = {}

        def done(pixel, n, estimate, covered):
            image.index_copy_(0, pixel[:n], estimate)
            coverage.index_copy_(0, pixel[:n], covered)
            bar.update(n * spp)

        try:
            with held():  # the first submits start the workers: they inherit SIGINT blocked, only we act on it
                for pixel, n in _chunks(scene, spp, options, job_rays):
                    jobs[pool.submit(_worker_render, digest, blob, pixel, n, spp, sampler, seed, options, dtype,
                                     max_depth, chunk_rays, jit_runs)] = (pixel, n)
            pending = set(jobs)
            while pending:  # woken at least every PARENT_CHECK_S, so a Ctrl-C is acted on within that time
                if INTERRUPTS:
                    raise KeyboardInterrupt
                finished, pending = concurrent.futures.wait(pending, timeout=PARENT_CHECK_S,
                                                            return_when=concurrent.futures.FIRST_COMPLETED)
                for job in finished:
                    done(*jobs[job], *job.result())
        except concurrent.futures.process.BrokenProcessPool as e:
            if not auto:
                raise
            _POOL.pop(workers, None)
            pool.shutdown(wait=False, cancel_futures=True)
            _AUTO_WORKERS_OFF.append(str(e))
            warnings.warn("render: worker processes failed to start (a script that renders outside `if __name__ == "
                          "\"__main__\":`?); tracing in this process from now on (workers=1 says so explicitly)",
                          RuntimeWarning, stacklevel=3)
            _render_into(scene, image, coverage, bar, spp, sampler, smp, options, device, dtype, seed, chunk_rays,
                         max_depth, 1)
        except BaseException:  # an interrupt: stop the workers now, not after their jobs (and at exit)
            # Taken before shutdown, which sets the pool's `_processes` to None (the loop found none, and the
            # command's exit waited for every running job: seconds to a minute after the Ctrl-C).
            processes = list((getattr(pool, "_processes", None) or {}).values())
            _POOL.pop(workers, None)
            pool.shutdown(wait=False, cancel_futures=True)
            for process in processes:
                process.terminate()
            raise
    else:
        for pixel, n in _chunks(scene, spp, options, chunk_rays):
            pixel = pixel.to(device)  # once: the samples are made from it and the results go back through it
            estimate, covered = _render_pixels(scene, pixel, smp, options, device, dtype, max_depth)
            image.index_copy_(0, pixel[:n], estimate[:n])
            coverage.index_copy_(0, pixel[:n], covered[:n])
            bar.update(n * spp)

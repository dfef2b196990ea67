"""Renders spread over a Ray cluster (`renderer render --cluster auto|ADDRESS`; the optional `distributed`
extra). The image is the one `renderer.render` makes for the same seed, bit for bit.

How: the same chunks of whole pixels as a single-process render (`renderer.render._chunks`, screen tiles in
tile order) are grouped into about `tasks_per_cpu` tasks per CPU of the cluster; the scene is put once into
Ray's object store (each worker fetches it once per node), every task traces its chunks with one torch
thread (`renderer.render._render_pixels`) and returns the estimates of its pixels, and the driver writes
them into the image as they arrive. Because a pixel's estimate depends only on its own samples (stateless
samplers keyed by pixel, sample and seed) and each pixel is traced in exactly one chunk, the split cannot
change the image.

Over N machines: throughput grows with the total number of cores as long as each task is long against
Ray's per-task overhead (about a millisecond) and the result transfer: each task returns 16 bytes per pixel
(float32 RGB + coverage), a 5472×3648 frame about 320 MB in total, gathered by the driver; the scene is
shipped once per node (a few KB, or the mesh arrays). The driver's single-threaded gathering and the
slowest task (the last tile) bound the speed-up; animation frames or parameter sweeps would be spread the
same way, one task per frame or parameter set, with no gathering bottleneck.
"""
from __future__ import annotations

import math
import os
from dataclasses import replace

import torch

from .progress import Progress
from .render import RenderResult, _chunks, _render_pixels
from .sampling import Sampler
from .scene import Scene


def connect(address: str = "auto"):
    """Import ray and connect: `auto` joins the cluster this machine belongs to, or starts a local one;
    any other value is a cluster address (`ray://host:10001` or `host:6379`). Returns the ray module."""
    try:
        import ray
    except ImportError as e:
        raise ImportError("--cluster needs ray: pip install -e '.[distributed]'") from e
    if ray.is_initialized():
        return ray
    kwargs = dict(ignore_reinit_error=True, log_to_driver=False, include_dashboard=False)
    if address == "auto":
        try:
            ray.init(address="auto", **kwargs)
        except (ConnectionError, RuntimeError):
            # No running cluster: a local one on this machine's cores. Workers import `renderer` from here.
            root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
            env = {"env_vars": {"PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])),
                                "OMP_NUM_THREADS": "1"}}
            ray.init(runtime_env=env, **kwargs)
    else:
        _check_reachable(address)
        ray.init(address=address, **kwargs)
    return ray


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """ConnectionError naming the address when nothing listens there (Ray itself retries for minutes)."""
    import socket

    hostport = address.split("://", 1)[-1]
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ConnectionError(f"--cluster {address}: expected auto or HOST:PORT (or ray://HOST:PORT)")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise ConnectionError(f"--cluster {address}: cannot reach {host}:{port} ({e.strerror or e})") from None


def _trace_chunks(scene: Scene, chunks, spp: int, sampler: str, seed: int, options, dtype, max_depth):
    """Estimates (n, 3) and coverage (n,) of the real pixels of `chunks` [(pixel, n), ...], concatenated."""
    torch.set_num_threads(1)
    smp = Sampler(sampler, spp, seed)
    est, cov = [], []
    for pixel, n in chunks:
        e, c = _render_pixels(scene, pixel, smp, options, "cpu", dtype, max_depth)
        est.append(e[:n])
        cov.append(c[:n])
    return torch.cat(est), torch.cat(cov)


def render_on_ray(scene: Scene, spp: int | None = None, sampler: str | None = None, *, address: str = "auto",
                  seed: int = 0, dtype=torch.float32, chunk_rays: int = 1 << 15, max_depth: int | None = None,
                  tasks_per_cpu: int = 4, progress: bool = False) -> RenderResult:
    """`renderer.render(scene, spp, sampler, seed=..., dtype=..., max_depth=...)` traced on a Ray cluster
    (CPU; see the module docstring). chunk_rays: camera samples per chunk, as in `render`."""
    ray = connect(address)
    W, H = scene.camera.width, scene.camera.height
    spp = scene.image.spp if spp is None else spp
    sampler = sampler or scene.image.sampler
    options = replace(scene.options, compile=False)
    chunks = list(_chunks(scene, spp, options, chunk_rays))
    cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
    n_tasks = min(len(chunks), cpus * tasks_per_cpu)
    per_task = math.ceil(len(chunks) / n_tasks)
    groups = [chunks[i:i + per_task] for i in range(0, len(chunks), per_task)]
    remote = ray.remote(num_cpus=1)(_trace_chunks)
    scene_ref = ray.put(scene)
    pending = {remote.remote(scene_ref, g, spp, sampler, seed, options, dtype, max_depth):
               torch.cat([p[:n] for p, n in g]) for g in groups}
    image = torch.empty(W * H, 3, dtype=dtype)
    coverage = torch.empty(W * H, dtype=dtype)
    bar = Progress(W * H * spp, "render (ray)", enabled=progress)
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            pixels = pending.pop(ref)
            estimate, covered = ray.get(ref)
            image.index_copy_(0, pixels, estimate)
            coverage.index_copy_(0, pixels, covered)
            bar.update(pixels.shape[0] * spp)
    return RenderResult(image.reshape(H, W, 3), coverage.reshape(H, W))

"""Renders spread over a Ray cluster (`renderer render --cluster auto|ADDRESS`; the optional `distributed`
extra). The image is the one `renderer.render` makes for the same seed, bit for bit.

How: the same chunks of whole pixels as a single-process render (`renderer.tracing.render._chunks`, screen tiles in
tile order) are grouped into about `tasks_per_cpu` tasks per CPU of the cluster; the scene is put once into
Ray's object store (each worker fetches it once per node), every task traces its chunks with one torch
thread (`renderer.tracing.render._render_pixels`) and returns the estimates of its pixels, and the driver writes
them into the image as they arrive. Because a pixel's estimate depends only on its own samples (stateless
samplers keyed by pixel, sample and seed) and each pixel is traced in exactly one chunk, the split cannot
change the image.

Over N machines: throughput grows with the total number of cores as long as each task is long against
Ray's per-task overhead (about a millisecond) and the result transfer: each task returns 16 bytes per pixel
(float32 RGB + coverage), a 5472×3648 frame about 320 MB in total, gathered by the driver; the scene is
shipped once per node (a few KB, or the mesh arrays). The driver's single-threaded gathering and the
slowest task (the last tile) bound the speed-up.

The same plumbing serves any list of independent jobs: `imap_on_cluster` / `map_on_cluster` run
`fn(shared, item)` for each item as Ray tasks (the `shared` object put into the object store once) and
give the results back in input order, or run them here one after another when no cluster is asked for;
a session started for the call is shut down after it, one the caller holds is left running. Users:
this render (unordered, tiles written as they come), `renderer animate --cluster` (a task per frame, or a
contiguous run of frames per CPU for beam tracing; `renderer.cli.animate`) and `tiltfit stability --cluster`
(a task per study; `tiltfit.experiments.cluster`). Costs per task, for shipping and for gathering: docs/speed.md.
"""
from __future__ import annotations

import contextlib
import math
import os

import torch

from camio.errors import os_reason
from camio.progress import Progress
from renderer.tracing.render import RenderResult, _chunks, _options, _render_pixels
from renderer.tracing.sampling import Sampler
from renderer.scene.model import Scene


def _import_ray():
    try:
        import ray
    except ImportError as e:
        raise ImportError("--cluster needs ray: pip install -e '.[distributed]'") from e
    return ray


def connect(address: str = "auto"):
    """Import ray and connect: `auto` joins the cluster this machine belongs to, or starts a local one;
    any other value is a cluster address (`ray://host:10001` or `host:6379`). Returns the ray module.
    When this process is already connected, that connection is used (an address is still checked)."""
    ray = _import_ray()
    if address != "auto":
        _check_reachable(address)
    if ray.is_initialized():
        return ray
    kwargs = dict(ignore_reinit_error=True, log_to_driver=False, include_dashboard=False)
    if address == "auto":
        try:
            ray.init(address="auto", **kwargs)
        except (ConnectionError, RuntimeError):
            # No running cluster: a local one on this machine's cores. Workers import `renderer` from here.
            root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
            env = {"env_vars": {"PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])),
                                "OMP_NUM_THREADS": "1"}}
            ray.init(runtime_env=env, **kwargs)
    else:
        ray.init(address=address, **kwargs)
    return ray


@contextlib.contextmanager
def cluster_session(address: str = "auto"):
    """`connect(address)` for the duration of a with-block; shuts Ray down afterwards only if this call
    started the connection (an enclosing session or the caller's own `ray.init` is left running)."""
    ray = _import_ray()
    started = not ray.is_initialized()
    connect(address)
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


def cluster_cpus(ray) -> int:
    """CPUs of the connected cluster (at least 1)."""
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


def _call(fn, shared, item, threads: int | None):
    """One task: `fn(shared, item)` with `threads` torch threads (None: the worker's setting), restored
    afterwards (Ray reuses its worker processes for other tasks)."""
    previous = torch.get_num_threads()
    if threads is not None and threads != previous:
        torch.set_num_threads(threads)
    try:
        return fn(shared, item)
    finally:
        if torch.get_num_threads() != previous:
            torch.set_num_threads(previous)


def imap_on_cluster(fn, items, cluster: str | None = None, *, shared=None, ordered: bool = True,
                    threads: int | None = 1):
    """Yield `(i, fn(shared, items[i]))` for every item: as Ray tasks (one CPU each) when `cluster` names one
    (`auto` or an address, see `connect`), else here, one after another, in input order.

    Args:
        fn: a module-level function (workers import it by name) of (shared, item); each call independent.
        items: the jobs (each pickled into its task; keep them small).
        cluster: None (run here), `auto` or a cluster address.
        shared: an object every call needs (scene, configuration): put into Ray's object store once.
        ordered: yield in input order, each result as soon as all earlier ones are in (True), or in the
            order the tasks finish (False).
        threads: torch threads inside each task [1: one task per core]; None leaves the worker's setting.
            Ignored when running here.
    Raises:
        ImportError (ray missing), ConnectionError (address not reachable); an exception raised by `fn` in
        a task is raised here as itself.
    """
    items = list(items)
    if cluster is None:
        for i, item in enumerate(items):
            yield i, fn(shared, item)
        return
    with cluster_session(cluster) as ray:
        remote = ray.remote(num_cpus=1)(_call)
        shared_ref = ray.put(shared)
        refs = [remote.remote(fn, shared_ref, item, threads) for item in items]
        index = {ref: i for i, ref in enumerate(refs)}
        finished, next_out, pending = {}, 0, list(refs)
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    i = index[ref]
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayTaskError as e:
                        cause = getattr(e, "cause", None)
                        raise (cause if isinstance(cause, Exception) else e) from None
                    if not ordered:
                        yield i, result
                    else:
                        finished[i] = result
                while ordered and next_out in finished:
                    yield next_out, finished.pop(next_out)
                    next_out += 1
        finally:
            for ref in pending:
                ray.cancel(ref)


def map_on_cluster(fn, items, cluster: str | None = None, *, shared=None, threads: int | None = 1) -> list:
    """`[fn(shared, item) for item in items]`, on a Ray cluster when `cluster` is given (see `imap_on_cluster`)."""
    return [result for _, result in imap_on_cluster(fn, items, cluster, shared=shared, threads=threads)]


# HTTP/2's client preface and an empty SETTINGS frame: a Ray head (GCS or Ray Client, both gRPC) answers
# with its own SETTINGS frame (type 4, the fourth byte of the frame header; RFC 9113 §3.4, §6.5).
_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00"
_HTTP2_SETTINGS = 4


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """ConnectionError naming the address, within `timeout` seconds, when nothing listens there or what
    answers does not speak gRPC as a Ray head does (Ray itself retries for minutes, or waits forever)."""
    import socket

    hostport = address.split("://", 1)[-1]
    host, _, port = hostport.rpartition(":")
    host = host.strip("[]")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConnectionError(f"--cluster {address[:80]}: expected auto or HOST:PORT (or ray://HOST:PORT), "
                              "PORT in 1..65535")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout) as sock:
            sock.sendall(_HTTP2_PREFACE)
            reply = sock.recv(9)
    except (UnicodeError, ValueError):  # a host name the resolver cannot encode (a label over 63 letters)
        raise ConnectionError(f"--cluster {address[:80]}: not a valid host name") from None
    except socket.timeout:
        raise ConnectionError(f"--cluster {address[:80]}: {host}:{port} does not answer as a Ray cluster "
                              f"(no reply within {timeout:g} s)") from None
    except OSError as e:
        raise ConnectionError(f"--cluster {address[:80]}: cannot reach {host}:{port} ({os_reason(e)})") from None
    if len(reply) < 4 or reply[3] != _HTTP2_SETTINGS:
        raise ConnectionError(f"--cluster {address[:80]}: {host}:{port} answers, but not as a Ray cluster "
                              "(no gRPC reply)")


def _trace_chunks(job, chunks):
    """Estimates (n, 3) and coverage (n,) of the real pixels of `chunks` [(pixel, n), ...], concatenated.
    job: (scene, spp, sampler, seed, options, dtype, max_depth), shared by every task."""
    scene, spp, sampler, seed, options, dtype, max_depth = job
    if options.intersector == "mitsuba":  # one Dr.Jit thread a task, as a local worker process has
        from renderer.mitsuba.intersect import set_jit_threads

        set_jit_threads(1)
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
    W, H = scene.camera.width, scene.camera.height
    spp = scene.image.spp if spp is None else spp
    sampler = sampler or scene.image.sampler
    options = _options(scene, None, False, None, "cpu", dtype)   # `auto` resolved here, so tasks take render's path
    chunks = list(_chunks(scene, spp, options, chunk_rays))
    with cluster_session(address) as ray:
        n_tasks = min(len(chunks), cluster_cpus(ray) * tasks_per_cpu)
        per_task = math.ceil(len(chunks) / n_tasks)
        groups = [chunks[i:i + per_task] for i in range(0, len(chunks), per_task)]
        image = torch.empty(W * H, 3, dtype=dtype)
        coverage = torch.empty(W * H, dtype=dtype)
        bar = Progress(W * H * spp, "render (ray)", enabled=progress)
        job = (scene, spp, sampler, seed, options, dtype, max_depth)
        for i, (estimate, covered) in imap_on_cluster(_trace_chunks, groups, address, shared=job, ordered=False):
            pixels = torch.cat([p[:n] for p, n in groups[i]])
            image.index_copy_(0, pixels, estimate)
            coverage.index_copy_(0, pixels, covered)
            bar.update(pixels.shape[0] * spp)
    return RenderResult(image.reshape(H, W, 3), coverage.reshape(H, W))

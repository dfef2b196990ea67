"""Fuzz corpus for the newer `renderer` inputs (issue 24): animation frames in the scene file, an empty
`objects` list, CSG and polyhedron sizes, lens distortion without an inverse, non-finite Mitsuba output and
`--cluster` addresses. Run in-process through tests/fuzz_harness.py: exit 0 with a finite output, or exit 2 and
one line `renderer: <file>: <field>: ...`; no traceback, hang or file left behind.
"""
from __future__ import annotations

import copy
import json
import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import fuzz_harness  # noqa: E402
import processes  # noqa: E402

BASE = {
    "image": {"width": 4, "height": 3, "spp": 1, "max_depth": 2, "background": [0.1, 0.1, 0.1]},
    "camera": {"type": "pinhole", "position": [0, 0, -5], "look_at": [0, 0, 0], "up": [0, -1, 0], "fov_deg": 40},
    "lights": [{"type": "point", "position": [2, -3, -4], "intensity": [20, 20, 20]}],
    "objects": [{"name": "ball", "shape": {"type": "sphere", "center": [0, 0, 0], "radius": 1},
                 "material": {"color": [0.8, 0.3, 0.2]}}],
}


def _scene(**changes) -> str:
    s = copy.deepcopy(BASE)
    for path, value in changes.items():
        node, keys = s, path.split("__")
        for k in keys[:-1]:
            node = node[int(k)] if isinstance(node, list) else node.setdefault(k, {})
        node[keys[-1]] = value
    return json.dumps(s)


def _render(scene: str, *extra, name, expect="refuse", fields=("scene.json",), output="out.exr"):
    return {"name": f"render/{name}", "category": "scene", "files": {"scene.json": scene}, "expect": expect,
            "fields": fields, "output": output,
            "argv": ["render", "{d}/scene.json", "-o", "{d}/" + output, "--quiet", *extra]}


def _animate(scene: str, *extra, name, expect="refuse", fields=("scene.json",)):
    return {"name": f"animate/{name}", "category": "animate", "files": {"scene.json": scene}, "expect": expect,
            "fields": fields, "output": "anim",
            "argv": ["animate", "{d}/scene.json", "--method", "trace", "-o", "{d}/anim", "--quiet", *extra]}


def _halfspaces(n: int) -> list:
    import math

    return [[math.cos(2 * math.pi * k / n), math.sin(2 * math.pi * k / n), 0.0, 1.0] for k in range(n)] + [
        [0, 0, 1, 1], [0, 0, -1, 1]]


def _cases() -> list[dict]:
    out = []
    for raw, expect in ((1e9, "refuse"), (70000, "refuse"), (1.5, "refuse"), (0, "refuse"), (2, "ok")):
        out.append(_animate(_scene(animation={"frames": raw, "step": 0.1}), name=f"frames={raw:g}", expect=expect,
                            fields=("scene.json", "animation.frames") if expect == "refuse" else ()))
    out.append(_render(_scene(objects=[]), name="objects-empty", fields=("scene.json", "objects")))
    out.append(_animate(_scene(objects=[], animation={"frames": 2, "step": 0.1}), name="objects-empty",
                        fields=("scene.json", "objects")))
    leaf = {"type": "polyhedron", "halfspaces": _halfspaces(6)}
    for n, expect in ((1500, "refuse"), (8, "ok")):
        shape = {"type": "csg", "op": "union", "children": [copy.deepcopy(leaf) for _ in range(n)]}
        out.append(_render(_scene(objects__0__shape=shape), name=f"csg-union-{n}", expect=expect,
                           fields=("scene.json", "objects[0].shape") if expect == "refuse" else ()))
    for n, expect in ((600, "refuse"), (40, "ok")):
        shape = {"type": "polyhedron", "halfspaces": _halfspaces(n)}
        out.append(_render(_scene(objects__0__shape=shape), name=f"polyhedron-{n}", expect=expect,
                           fields=("scene.json", "halfspaces") if expect == "refuse" else ()))
    for name, coeffs in (("k1=1e30", [1e30, 0, 0, 0, 0]), ("k1=-1e30", [-1e30, 0, 0, 0, 0]),
                         ("k4=-1e6", [0, 0, 0, 0, 0, -1e6, 0, 0])):
        out.append(_render(_scene(camera__distortion={"model": "brown_conrady", "coefficients": coeffs}),
                           name=f"distortion-{name}", fields=("scene.json", "distortion")))
    out.append(_render(_scene(camera__distortion={"model": "brown_conrady", "coefficients": [-0.1, 0.01, 0, 0, 0]}),
                       name="distortion-ok", expect="ok", fields=()))
    animated = _scene(animation={"frames": 2, "step": 0.1})
    for step, expect in (("1e30", "refuse"), ("1e7", "refuse"), ("-1e30", "refuse"), ("0.5", "ok")):
        out.append(_animate(animated, "--step", step, name=f"step={step}", expect=expect,
                            fields=("--step",) if expect == "refuse" else ()))
    # A light whose float32 radiance overflows near the surface: refused or finite, by either backend.
    hot = _scene(lights__0__intensity=[3e38] * 3, lights__0__position=[0, 0, -1.2])
    out.append(_render(hot, name="light-3e38-torch", expect="either", fields=("scene.json",)))
    out.append(_render(hot, "--backend", "mitsuba", name="light-3e38-mitsuba", expect="either",
                       fields=("scene.json",)))
    for host in ("a" * 40, "a" * 300, "a" * 70 + ":6379", "[::1", "host:99999", "host:port", ":"):
        out.append(_render(_scene(), "--cluster", host, name=f"cluster={host[:5]}-{len(host)}", fields=("--cluster",)))
    return out


CASES = fuzz_harness.unique(_cases())


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_fuzz_case(case):
    fuzz_harness.check(case, "renderer")


@pytest.fixture
def not_ray_port():
    """A local TCP port that accepts connections and answers like an HTTP/1 server, then one that never
    answers: (port_http, port_silent)."""
    import socket
    import threading

    servers, stop = [], threading.Event()

    def serve(sock, reply):
        sock.settimeout(0.1)
        while not stop.is_set():
            try:
                conn, _ = sock.accept()
            except OSError:
                continue
            if reply:
                conn.sendall(reply)
                conn.close()
            else:
                servers.append(conn)  # held open, silent

    ports = []
    for reply in (b"HTTP/1.1 400 Bad Request\r\n\r\n", b""):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        s.listen()
        servers.append(s)
        ports.append(s.getsockname()[1])
        threading.Thread(target=serve, args=(s, reply), daemon=True).start()
    yield ports
    stop.set()
    for s in servers:
        s.close()


@pytest.mark.parametrize("command", ["render", "animate"])
@pytest.mark.parametrize("server", ["http", "silent"])
def test_cluster_port_that_is_not_ray_fails_fast_with_one_line(tmp_path, monkeypatch, not_ray_port, command, server):
    """`--cluster 127.0.0.1:PORT` where PORT answers but is not a Ray head: one line naming --cluster and exit 2
    within the probe's timeout (Ray itself would wait for minutes), nothing written."""
    import functools
    import time

    from renderer.tracing import distributed
    from renderer.cli.main import main

    monkeypatch.setattr(distributed, "_check_reachable",
                        functools.partial(distributed._check_reachable, timeout=1.0))
    port = not_ray_port[0 if server == "http" else 1]
    (tmp_path / "scene.json").write_text(_scene(animation={"frames": 2, "step": 0.1}))
    out = tmp_path / ("out.exr" if command == "render" else "anim")
    argv = [command, tmp_path / "scene.json", "-o", out, "--quiet", "--cluster", f"127.0.0.1:{port}"]
    if command == "animate":
        argv += ["--method", "trace"]
    t0 = time.perf_counter()
    rc, err = fuzz_harness.run_command(main, argv, timeout_s=60)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "--cluster" in lines[0] and "Ray" in lines[0], f"exit {rc}: {err!r}"
    assert time.perf_counter() - t0 < 10, f"took {time.perf_counter() - t0:.1f} s to refuse"
    assert sorted(os.listdir(tmp_path)) == ["scene.json"], f"left: {os.listdir(tmp_path)}"


def _children(pid: int) -> set[int]:
    out = set()
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out |= {int(x) for x in f.read().split()}
    except OSError:
        pass
    return out


@pytest.mark.slow
@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="reads the process tree from /proc")
def test_workers_end_when_renderer_render_is_killed(tmp_path):
    """SIGKILL of `renderer render` (which cannot be caught): its worker processes end by themselves within a
    few seconds instead of living on as orphans."""
    import subprocess
    import time

    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one core: renders run without worker processes")
    # Between two mirrors every ray bounces max_depth times: each worker job runs for many seconds, so a worker
    # that only ends when it next talks to its parent would outlive it.
    mirror = {"color": [0.9, 0.9, 0.9], "reflect": 1.0}
    scene = json.loads(_scene(objects=[
        {"name": "a", "shape": {"type": "plane", "point": [0, 0, 2], "normal": [0, 0, -1]}, "material": mirror},
        {"name": "b", "shape": {"type": "plane", "point": [0, 0, -8], "normal": [0, 0, 1]}, "material": mirror}]))
    scene["image"].update(width=512, height=512, spp=64, max_depth=64)  # 2^24 rays, jobs of 2^20
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    proc = subprocess.Popen([sys.executable, "-m", "renderer", "render", str(tmp_path / "scene.json"), "-o",
                             str(tmp_path / "out.exr"), "--quiet"], env=env, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline, workers = time.time() + 120, set()
        while time.time() < deadline and len(workers) < 2 and proc.poll() is None:
            time.sleep(0.2)
            workers = {c for c in _children(proc.pid) if "spawn_main" in open(f"/proc/{c}/cmdline").read()}
        if not workers:
            pytest.skip("the render finished or started no workers before it could be killed")
        time.sleep(0.5)
        proc.kill()
        proc.wait()
        # A worker still importing torch on a loaded machine starts its watchdog late: allow 30 s (the orphans
        # this guards against lived on for over 20 minutes).
        alive = processes.kill_left_running(workers, within_s=30, poll_s=0.2)
        assert not alive, f"worker processes {alive} outlived their killed parent by 30 s"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not [n for n in os.listdir(tmp_path) if n != "scene.json"], f"left: {os.listdir(tmp_path)}"



@pytest.mark.parametrize("quiet", [True, False])
def test_compile_under_quiet_prints_no_torch_warnings(tmp_path, monkeypatch, quiet):
    """issue 33 §4: `--compile --quiet` printed 32 lines of torch.compile's warnings. torch.compile is replaced by
    one that logs a dynamo warning and raises an inductor UserWarning on every call (as recompilations do), so
    the test runs in seconds. What torch's own log handler and the warnings machinery let through is recorded:
    nothing under --quiet (and stderr is empty); both without it (the negative control)."""
    import logging
    import warnings

    import torch

    from renderer.cli.main import main

    def noisy_compile(fn, *args, **kwargs):
        def run(*a, **k):
            logging.getLogger("torch._dynamo.convert_frame").warning("torch._dynamo hit config.recompile_limit (8)")
            warnings.warn_explicit("TensorFloat32 tensor cores", UserWarning, "torch/_inductor/utils.py", 1,
                                   module="torch._inductor.utils")
            return fn(*a, **k)
        return run

    class Collect(logging.Handler):  # stands beside torch's own stderr handler on the dynamo logger
        def __init__(self):
            super().__init__()
            self.lines = []

        def emit(self, record):
            self.lines.append(record.getMessage())

    import renderer.scene.model
    import renderer.tracing.fused

    monkeypatch.setattr(torch, "compile", noisy_compile)
    # Functions an earlier test in this process compiled are cached: start without them, so the stand-in runs.
    monkeypatch.setattr(renderer.scene.model, "_COMPILED", {})
    monkeypatch.setattr(renderer.tracing.fused, "_COMPILED", {})
    scene = json.loads(_scene())
    scene["camera"] = {"type": "thin_lens", "position": [0, 0, -5], "look_at": [0, 0, 0], "w": 1, "U": 5, "d": 0.2,
                       "sensor_size": [0.8, 0.6], "theta_F_deg": 5}
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    argv = ["render", tmp_path / "scene.json", "-o", tmp_path / "out.exr", "--compile"] + (["--quiet"] if quiet else [])
    dynamo, collect = logging.getLogger("torch._dynamo"), Collect()
    dynamo.addHandler(collect)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rc, err = fuzz_harness.run_command(main, argv)
    finally:
        dynamo.removeHandler(collect)
    assert rc == 0, f"exit {rc}: {err}"
    torch_warnings = [w for w in caught if "TensorFloat32" in str(w.message)]
    if quiet:
        assert not collect.lines and not torch_warnings, \
            f"--quiet let through {len(collect.lines)} log lines and {len(torch_warnings)} warnings"
        assert not err.strip(), f"--quiet printed {len(err.splitlines())} lines: {err[:300]!r}"
    else:
        assert collect.lines and torch_warnings, "the stand-in's warnings were silenced without --quiet"
    assert not collect.filters, "a filter was left on torch's log handlers"

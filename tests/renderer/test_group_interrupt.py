"""Ctrl-C to the whole process group of `renderer render` while its worker processes start (issue 24): a
terminal's Ctrl-C reaches the workers too, which printed their own KeyboardInterrupt tracebacks, and a Ctrl-C
landing as the pool started was dropped (the image written, exit 0). Each case sends SIGINT to the group a
given time after the first worker process appears and asserts one line `renderer: interrupted`, exit 130, no
image and no process left behind. benchmarks/robustness/probe_group_interrupt.py runs the same at more delays. And the
cause of the dropped Ctrl-C: one landing while Mitsuba loads. And an interrupt reaching the command alone (as
`kill -INT` or a supervisor's SIGTERM does): its workers are terminated at once, not after their jobs."""
import os
import signal
import subprocess
import sys
import time

import pytest

from renderer.scene.file import load_scene
from renderer.tracing.render import _cores

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from processes import children as _children  # noqa: E402  (shared with benchmarks/robustness/probe_group_interrupt.py)
from processes import is_worker as _is_worker  # noqa: E402
from processes import kill_left_running  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENE = os.path.join(ROOT, "benchmarks", "scenes", "speed_thin_lens.json")

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not hasattr(os, "killpg"), reason="POSIX process groups")]


@pytest.mark.skipif(_cores() < 2, reason="needs worker processes (2 cores)")
@pytest.mark.parametrize("delay_s", [0.0, 0.4, 0.9])
def test_group_sigint_while_workers_start(tmp_path, delay_s):
    out = tmp_path / "img.png"
    # Python's own handler here: a test run from a background job inherits SIGINT ignored, which the renderer
    # would inherit too (and never see the Ctrl-C).
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        # Our own tracer: with Embree the speed scene takes the Dr.Jit path, which starts no worker processes.
        p = subprocess.Popen([sys.executable, "-m", "renderer", "render", SCENE, "-o", str(out), "--spp", "64",
                              "--set", "image.width=512", "--set", "image.height=512", "--intersector", "torch"],
                             stderr=subprocess.PIPE,
                             text=True, start_new_session=True, cwd=ROOT,
                             env={**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")})
    finally:
        signal.signal(signal.SIGINT, previous)
    seen, t0 = set(), time.time()
    try:
        while p.poll() is None and time.time() - t0 < 120 and not any(_is_worker(c) for c in seen):
            seen |= _children(p.pid)
            time.sleep(0.02)
        assert p.poll() is None, "the render ended before its workers started"
        time.sleep(delay_s)
        seen |= _children(p.pid)
        os.killpg(p.pid, signal.SIGINT)
        while p.poll() is None and time.time() - t0 < 120:
            seen |= _children(p.pid)
            time.sleep(0.05)
        err = p.communicate(timeout=60)[1]
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    left = kill_left_running(seen, within_s=5, poll_s=0.1)
    assert p.returncode == 130, f"exit {p.returncode} (the Ctrl-C was dropped?): {err[-500:]}"
    assert "Traceback" not in err and "Exception ignored" not in err, f"a traceback on stderr: {err[-2000:]}"
    assert err.strip().splitlines() == ["renderer: interrupted"], f"one line on stderr: {err[-1000:]!r}"
    assert not out.exists(), "no image written after the Ctrl-C"
    assert not left, f"processes left running after the render ended: {left}"


_AUTO_ENGINE = """
import os, signal, sys, threading, time
import torch
from renderer import load_scene
from renderer.mitsuba.intersect import auto_engine
scene = load_scene(sys.argv[1])
threading.Timer(float(sys.argv[2]), lambda: os.kill(os.getpid(), signal.SIGINT)).start()
try:
    auto_engine(scene, "cpu", torch.float32)
    time.sleep(5)
except KeyboardInterrupt:
    print("interrupted", flush=True)
    sys.exit(130)
print("not interrupted", flush=True)
"""


@pytest.mark.parametrize("delay_s", [0.1, 0.3, 1.2])
def test_sigint_while_mitsuba_loads_is_not_read_as_no_mitsuba(delay_s):
    """A Ctrl-C while `intersector="auto"` imports Mitsuba and probes its LLVM variant (on main it was turned
    into an ImportError inside the extension's import, read as "no Mitsuba here", and dropped: the render went
    on with our tracer) raises KeyboardInterrupt once that step is done."""
    p = subprocess.run([sys.executable, "-c", _AUTO_ENGINE, SCENE, str(delay_s)], capture_output=True, text=True,
                       timeout=120, cwd=ROOT, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
                       env={**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")})
    assert p.returncode == 130 and p.stdout.strip() == "interrupted", \
        f"SIGINT {delay_s} s into auto_engine: exit {p.returncode}, {p.stdout.strip()!r}, {p.stderr[-800:]}"


@pytest.mark.skipif(_cores() < 2, reason="needs worker processes (2 cores)")
def test_an_interrupt_ends_the_worker_processes_at_once(monkeypatch):
    """A render interrupted while its workers trace terminates them then and there, not after their running
    jobs. The worker processes were read from the pool after `shutdown`, which had emptied it: none were
    terminated, and a `renderer render` signalled alone (not its group) exited only once every running job
    had ended (5-20 s after the signal here). Between two mirrors every ray bounces max_depth times, so a job
    runs far longer than the 5 s allowed."""
    import threading

    import renderer.tracing.render as render_module
    from camio.interrupts import INTERRUPTS
    from renderer import render

    monkeypatch.setattr(render_module, "_POOL", {})  # a pool of its own, not one an earlier test left running
    earlier = {c for c in _children(os.getpid()) if _is_worker(c)}

    mirror = {"color": [0.9, 0.9, 0.9], "reflect": 1.0}
    scene = load_scene({
        "image": {"width": 256, "height": 256, "spp": 64, "max_depth": 64},
        "camera": {"type": "pinhole", "fov_deg": 50},
        "lights": [{"type": "ambient", "intensity": [0.1, 0.1, 0.1]}],
        "objects": [
            {"name": "a", "shape": {"type": "plane", "point": [0, 0, 2], "normal": [0, 0, -1]}, "material": mirror},
            {"name": "b", "shape": {"type": "plane", "point": [0, 0, -8], "normal": [0, 0, 1]}, "material": mirror}]})
    workers: set = set()

    def interrupt_once_the_workers_run():
        deadline = time.time() + 120
        while time.time() < deadline and len(workers) < 2:
            workers.update(c for c in _children(os.getpid()) if _is_worker(c) and c not in earlier)
            time.sleep(0.05)
        time.sleep(1.0)  # by now the pool has queued a job for each worker
        INTERRUPTS.append(signal.SIGINT)  # as the `renderer` command's SIGINT handler does

    watcher = threading.Thread(target=interrupt_once_the_workers_run, daemon=True)
    watcher.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            render(scene, workers=2, intersector="torch")
    finally:
        INTERRUPTS.clear()
    watcher.join(timeout=5)
    assert len(workers) == 2, f"worker processes seen: {workers}"
    left = kill_left_running(workers, within_s=5, poll_s=0.05)
    assert not left, f"worker processes {left} still ran 5 s after the interrupt"

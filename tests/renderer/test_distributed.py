"""Renders on a local Ray cluster (renderer/tracing/distributed.py) give the single-process image bit for bit."""
import numpy as np
import pytest
import torch

ray = pytest.importorskip("ray")

from renderer import render  # noqa: E402
from renderer.tracing.distributed import render_on_ray  # noqa: E402
from renderer.scene.file import load_scene  # noqa: E402

SCENES = {"tilted thin lens": ("tilt_fig9b", ["image.width=40", "image.height=30", "image.spp=4"]),
          "layers": ("fig10", ["image.width=32", "image.height=24", "image.spp=2"])}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SCENES))
def test_ray_render_equals_single_process(cluster, name):
    """Same seed, same image: every pixel equal, with chunks small enough to make many tasks (a split
    that changed sampling or order would show)."""
    from renderer.cli.main import resolve_scene

    path, overrides = SCENES[name]
    scene = load_scene(resolve_scene(path), overrides)
    ours = render(scene, seed=7)
    spread = render_on_ray(scene, seed=7, chunk_rays=256)
    assert torch.equal(spread.image, ours.image), (
        f"{name}: max |diff| {float((spread.image - ours.image).abs().max()):.3g}")
    assert torch.equal(spread.coverage, ours.coverage), f"{name}: coverage differs"
    other_seed = render_on_ray(scene, seed=8, chunk_rays=256)
    assert not torch.equal(other_seed.image, ours.image), f"{name}: the seed should change the image"


@pytest.mark.slow
def test_cli_cluster_flag_writes_the_same_image(cluster, tmp_path):
    """`renderer render --cluster auto` (joining the running local cluster) writes the single-process image."""
    from renderer.cli.main import main, resolve_scene
    from camio.files import read_image

    overrides = ["image.width=24", "image.height=16", "image.spp=2"]
    out = str(tmp_path / "c.exr")
    args = ["render", "tilt_fig9b", "-o", out, "--cluster", "auto", "--quiet"]
    assert main(args + sum((["--set", o] for o in overrides), [])) == 0, "exit status"
    expected = render(load_scene(resolve_scene("tilt_fig9b"), overrides)).image.numpy()
    got = read_image(out)[..., :3]
    assert abs(got - expected).max() < 1e-6, f"max |diff| {abs(got - expected).max():.3g}"


# ------------------------------------------------------------------------------ renderer animate --cluster

ANIMATIONS = {"trace": ("tilt_fig9b", 3, 5.0, ["image.width=24", "image.height=16", "image.spp=2"]),
              "beam": ("beam_fig2", 5, 0.35, ["image.width=48", "image.height=36"])}


def _animate_frames(monkeypatch, tmp_path, method, cluster):
    """animate() with the float frames the driver writes captured: ({frame file: image}, rows)."""
    import renderer.cli.animate as an
    from renderer.cli.main import resolve_scene

    written = {}
    monkeypatch.setattr(an, "write_image", lambda path, image: written.__setitem__(
        path.rsplit("/", 1)[-1], np.array(image)))
    scene, frames, step, overrides = ANIMATIONS[method]
    rows = an.animate(resolve_scene(scene), method, frames, step, str(tmp_path / (cluster or "here")), overrides,
                      progress=False, seed=5, cluster=cluster)
    return written, rows


@pytest.mark.parametrize("method", sorted(ANIMATIONS))
def test_animate_on_cluster_equals_single_process(cluster, monkeypatch, tmp_path, method):
    """Frames as Ray tasks (trace: one per frame; beam: one contiguous run per CPU, the second starting at
    frame 2, where the single sequence re-determines nothing) give the frames of one process, bit for bit,
    written in order, and the same frames.csv apart from the timings."""
    here, rows_here = _animate_frames(monkeypatch, tmp_path, method, None)
    spread, rows_spread = _animate_frames(monkeypatch, tmp_path, method, "auto")
    assert list(spread) == list(here) == [f"frame_{k:04d}.png" for k in range(len(here))], "frames written in order"
    for name in here:
        assert np.array_equal(spread[name], here[name]), (
            f"{method} {name}: max |diff| {np.abs(spread[name] - here[name]).max():.3g}")
    assert not np.array_equal(here["frame_0000.png"], here["frame_0002.png"]), "the camera should move"
    untimed = [{k: v for k, v in r.items() if k not in ("seconds", "segment_seconds")} for r in rows_here]
    assert [{k: v for k, v in r.items() if k not in ("seconds", "segment_seconds")} for r in rows_spread] == untimed, (
        f"{method}: frames.csv rows differ")
    if method == "beam":
        assert [r["redetermined"] for r in rows_here] == [1, 0, 0, 1, 0], "beam_fig2 crosses a plane before frame 3"


def test_contiguous_runs_cover_every_frame_once():
    from renderer.cli.animate import contiguous_runs

    for frames, workers in ((5, 2), (3, 8), (10, 3), (1, 1)):
        runs = contiguous_runs(frames, workers)
        assert [k for a, b in runs for k in range(a, b)] == list(range(frames)), f"{frames} frames, {workers} workers"
        assert len(runs) == min(frames, workers), f"{frames} frames on {workers} workers: {runs}"
        assert max(b - a for a, b in runs) - min(b - a for a, b in runs) <= 1, f"unbalanced runs {runs}"


def test_map_on_cluster_here_and_on_ray_agree(cluster):
    """The generic helper: results in input order, here and as tasks; a task's exception comes back as itself."""
    import operator

    from renderer.tracing.distributed import imap_on_cluster, map_on_cluster

    items = [3, 1, 2, 0]
    assert map_on_cluster(operator.mul, items, None, shared=10) == [30, 10, 20, 0], "here"
    assert map_on_cluster(operator.mul, items, "auto", shared=10) == [30, 10, 20, 0], "on Ray"
    assert sorted(imap_on_cluster(operator.mul, items, "auto", shared=10, ordered=False)) == [
        (0, 30), (1, 10), (2, 20), (3, 0)], "unordered: every (index, result) once"
    with pytest.raises(ZeroDivisionError):
        map_on_cluster(operator.truediv, [1, 0], "auto", shared=10)


def test_cli_animate_unreachable_cluster_is_one_line(tmp_path, capsys):
    """A bad --cluster address: one line naming it, exit 2, no output folder left behind."""
    from renderer.cli.main import main

    out = tmp_path / "frames"
    status = main(["animate", "beam_fig2", "--method", "trace", "--frames", "2", "-o", str(out),
                   "--cluster", "127.0.0.1:1", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert status == 2, f"exit status {status}"
    assert err.count("\n") == 0 and "127.0.0.1:1" in err, f"one line naming the address: {err!r}"
    assert not out.exists(), "no output folder"


def test_cli_animate_cluster_flag_writes_the_same_frames(cluster, tmp_path):
    """`renderer animate --cluster auto --seed 3` writes the frames (8-bit values) and frames.csv columns of
    the same command without --cluster; the seed reaches the tasks."""
    import csv

    from renderer.cli.main import main
    from camio.files import read_image

    args = ["animate", "tilt_fig9b", "--method", "trace", "--frames", "2", "--step", "5", "--quiet",
            "--set", "image.width=24", "--set", "image.height=16", "--set", "image.spp=2"]
    outputs = {}
    for name, extra in (("here", ["--seed", "3"]), ("ray", ["--seed", "3", "--cluster", "auto"]),
                        ("other_seed", ["--seed", "4"])):
        assert main(args + extra + ["-o", str(tmp_path / name)]) == 0, f"{name}: exit status"
        with open(tmp_path / name / "frames.csv", newline="") as f:
            table = [{k: v for k, v in r.items() if k != "seconds"} for r in csv.DictReader(f)]
        outputs[name] = ([read_image(str(tmp_path / name / f"frame_{k:04d}.png")) for k in range(2)], table)
    for k in range(2):
        assert np.array_equal(outputs["ray"][0][k], outputs["here"][0][k]), f"frame {k} differs"
    assert outputs["ray"][1] == outputs["here"][1], "frames.csv differs beyond the timings"
    assert not np.array_equal(outputs["other_seed"][0][1], outputs["here"][0][1]), "--seed should change the frame"

"""Renders on a local Ray cluster (renderer/distributed.py) give the single-process image bit for bit."""
import pytest
import torch

ray = pytest.importorskip("ray")

from renderer import render  # noqa: E402
from renderer.distributed import render_on_ray  # noqa: E402
from renderer.scenefile import load_scene  # noqa: E402

SCENES = {"tilted thin lens": ("tilt_fig9b", ["image.width=40", "image.height=30", "image.spp=4"]),
          "layers": ("fig10", ["image.width=32", "image.height=24", "image.spp=2"])}


@pytest.fixture(scope="module")
def cluster():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"OMP_NUM_THREADS": "1"}})
    yield ray
    ray.shutdown()


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SCENES))
def test_ray_render_equals_single_process(cluster, name):
    """Same seed, same image: every pixel equal, with chunks small enough to make many tasks (a split
    that changed sampling or order would show)."""
    from renderer.cli import resolve_scene

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
    from renderer.cli import main, resolve_scene
    from renderer.io import read_image

    overrides = ["image.width=24", "image.height=16", "image.spp=2"]
    out = str(tmp_path / "c.exr")
    args = ["render", "tilt_fig9b", "-o", out, "--cluster", "auto", "--quiet"]
    assert main(args + sum((["--set", o] for o in overrides), [])) == 0, "exit status"
    expected = render(load_scene(resolve_scene("tilt_fig9b"), overrides)).image.numpy()
    got = read_image(out)[..., :3]
    assert abs(got - expected).max() < 1e-6, f"max |diff| {abs(got - expected).max():.3g}"
